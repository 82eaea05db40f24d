"""The MAP searches of one fit (``init="map"``, ``modes="weighted"``) and what they found."""

import warnings
from dataclasses import dataclass

from . import laplace as _laplace
from .mixture import kept, laplace_log_mass, mode_weights
from .mode import best_map, modes_json
from .space import Unconstrained


@dataclass
class Search:
    """``starts`` searches seeded by ``seed`` (``best_map``); the modes found (JSON, the tree's
    ``map_modes``) and, with ``weighted``, the modes fitted and their weights (``mode_weights``)."""

    starts: int
    seed: int
    progress: bool
    weighted: bool = False
    modes: str | None = None
    weights: str | None = None

    @classmethod
    def of(cls, method):
        return cls(method.map_starts, method.seed, method.progress, method.modes == "weighted")

    def map_init(self, model, data, init):
        """An init strategy at the MAP."""
        space = Unconstrained(model, data, init)
        result, self.modes = best_map(space, model, data, init, self.starts, self.seed, progress=self.progress)
        return _laplace.init_at(space, result[0])

    def laplace_start(self, model, data, init, observed):
        """(init strategy at the MAP, the space, the Laplace Gaussian there or None where the
        Hessian is not positive definite (with a warning), gradient evaluations)."""
        space, found, evaluations = _laplace.modes(model, data, init, observed, "exact", self.progress,
                                                   self.starts, self.seed)
        self.modes = modes_json(space, found)
        z, _, _, h = found[0]
        try:
            gaussian = _laplace.Gaussian(z, h, space.labels)
        except _laplace.NotPositiveDefiniteHessian as error:
            warnings.warn(f"{error}. SVI starts at the MAP with the guide's default scale instead", stacklevel=4)
            gaussian = None
        return _laplace.init_at(space, z), space, gaussian, evaluations

    def modes_to_fit(self, model, data, init, observed, hessian):
        """(space, the modes worth fitting (``mixture.kept``), their Laplace log masses, gradient
        evaluations of the searches); every mode found goes to ``modes``."""
        space, found, evaluations = _laplace.modes(model, data, init, observed, hessian, self.progress,
                                                   self.starts, self.seed, warn=False)
        self.modes = modes_json(space, found)
        masses = [laplace_log_mass(u, h) for _, u, _, h in found]
        chosen = kept(found, masses)
        return space, [found[i] for i in chosen], [masses[i] for i in chosen], evaluations

    def record_weights(self, space, fitted, laplace_masses, masses, counts, **extra):
        weights = mode_weights(masses)
        self.weights = modes_json(space, fitted, laplace_log_mass=laplace_masses, log_mass=list(masses),
                                  weight=weights.tolist(), draws=[int(c) for c in counts], **extra)
