"""Linear algebra that knows nothing of peridynamics: sparse SPD factors on a pattern
(``sparse``), the differentiable solve whose adjoint is one more solve (``adjoint``), assembly of Gram sums on a pattern (``assembly``, ``stiffness_solver``), factors
(``factors``), low-rank updates (``woodbury``), block half solves (``trailing``), lock-step
batching of half solves (``lockstep``) and the settings they run under (``config``)."""
from bayespd.linalg.config import LinalgSettings, current_settings, set_defaults, settings

__all__ = ["LinalgSettings", "current_settings", "set_defaults", "settings"]
