"""Linear algebra that knows nothing of peridynamics: sparse SPD solves with an adjoint
(``sparse``), assembly of Gram sums on a pattern (``assembly``, ``stiffness_solver``), factors
(``factors``), low-rank updates (``woodbury``), block half solves (``trailing``), lock-step
batching of half solves (``lockstep``) and the settings they run under (``config``)."""
from bayespd.linalg.config import LinalgSettings, current_settings, set_defaults, settings

__all__ = ["LinalgSettings", "current_settings", "set_defaults", "settings"]
