"""The pieces of the tutorial's Bayesian step that are not the user's code: the horizon held at
the Tikhonov value (a scene whose parameters are K, G only), the term's one feature log(G / K),
and the approximation-error term of the plain LPS against the FE peer (Kaipio & Somersalo 2007;
``bp.estimate_discrepancy`` with ``relative=True``: under prescribed loads the relative error
depends on the moduli only through G / K, so one design over nu serves every E).
"""
from __future__ import annotations

import numpy as np
import torch

import bayespd as bp


class AtHorizon:
    """``scene`` (full or ``bp.ReducedScene``) with delta held at ``delta``: parameters K, G."""

    param_names = ("K", "G")

    def __init__(self, scene, delta: float):
        self.scene, self.delta = scene, float(delta)
        self.material, self.particles, self.observation = scene.material, scene.particles, scene.observation

    def predict(self, params: dict) -> torch.Tensor:
        return self.scene.predict({**params, "delta": self.delta})

    def diagnostics(self, draws: dict) -> dict:
        """The reduced scene's error estimate per draw (none for a full scene)."""
        report = getattr(self.scene, "diagnostics", None)
        if report is None:
            return {}
        shape = np.shape(draws["K"])[:2]
        return report({**draws, "delta": np.full(shape, self.delta)})


class RatioFeature:
    """phi(params) = (log(G / K),): the relative error's only dependence at fixed delta."""

    def __call__(self, params: dict) -> torch.Tensor:
        K, G = (torch.as_tensor(params[k], dtype=torch.float64) for k in ("K", "G"))
        return torch.log(G / K).reshape(1)


def fe_error_term(fe_at, scene, nus, inside, young: float = 4000.0) -> bp.Discrepancy:
    """The relative error of ``scene`` (an AtHorizon) against the FE peer ``fe_at(young, nu,
    points)`` on a design of Poisson ratios ``nus`` (smooth trend in log(G / K)); at the
    observation points ``inside(points)`` leaves out (a hole: masked data) the error is 0."""
    points = scene.observation.points.numpy() if torch.is_tensor(scene.observation.points) \
        else np.asarray(scene.observation.points)
    draws = [dict(zip(("K", "G"), map(float, bp.moduli_from_young(young, nu)))) for nu in nus]

    keep = inside(points)

    def reference(params):
        E, nu = bp.young_from_moduli(params["K"], params["G"])
        u = scene.predict(params).clone()
        u[torch.as_tensor(keep)] = torch.as_tensor(fe_at(float(E), float(nu), points[keep]))
        return u

    with torch.no_grad():
        return bp.estimate_discrepancy(reference, scene.predict, draws, dependence="smooth",
                                       features=RatioFeature(), relative=True, explained=0.9999,
                                       points=scene.observation.points)


def young_intervals(tree, level: float = 0.9) -> dict:
    """Mean and central ``level`` interval of E and nu over the posterior draws of K, G."""
    post = tree["posterior"]
    E, nu = bp.young_from_moduli(post["K"].values.reshape(-1), post["G"].values.reshape(-1))
    q = [(1 - level) / 2, (1 + level) / 2]
    return {k: {"mean": float(np.mean(v)), "sd": float(np.std(v)), "interval_90": np.quantile(v, q).tolist()}
            for k, v in (("E", np.asarray(E)), ("nu", np.asarray(nu)))}
