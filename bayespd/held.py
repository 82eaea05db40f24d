"""A scene with some of its parameters held at given values (e.g. the horizon at a Tikhonov
estimate): a model then infers only the rest. Works for a full ``Scene`` and a
``ReducedScene`` alike; the reduced scene's per-draw diagnostics get the held values too.

    scene = bp.Held(bp.ReducedScene(plate, draws, tol), delta=3 * h)   # param_names ('K', 'G')
"""
from __future__ import annotations

import numpy as np


class Held:
    """``scene`` with the parameters in ``values`` fixed; ``param_names`` are the others."""

    def __init__(self, scene, **values):
        unknown = set(values) - set(scene.param_names)
        if unknown:
            raise ValueError(f"cannot hold {sorted(unknown)}: the scene's parameters are {list(scene.param_names)}")
        if not values:
            raise ValueError("name at least one parameter to hold, e.g. Held(scene, delta=3.0)")
        self.scene, self.values = scene, {k: float(v) for k, v in values.items()}
        self.param_names = tuple(k for k in scene.param_names if k not in values)
        self.material, self.particles, self.observation = scene.material, scene.particles, scene.observation

    def predict(self, params: dict):
        return self.scene.predict({**params, **self.values})

    def diagnostics(self, draws: dict) -> dict:
        """The scene's per-draw diagnostics (a reduced scene's error estimate; none for a full one)."""
        report = getattr(self.scene, "diagnostics", None)
        if report is None:
            return {}
        shape = np.shape(draws[self.param_names[0]])
        return report({**draws, **{k: np.full(shape, v) for k, v in self.values.items()}})
