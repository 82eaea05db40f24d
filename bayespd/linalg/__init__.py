"""Linear algebra that knows nothing of peridynamics: sparse SPD factors on a pattern
(``sparse``), the differentiable solve whose adjoint is one more solve (``adjoint``), assembly of Gram sums on a pattern (``assembly``, ``stiffness_solver``), factors
(``factors``), low-rank updates (``woodbury``), block half solves (``trailing``), lock-step
batching of half solves (``lockstep``), algebraic multigrid (``amg``) and the settings they run under, the choice of solver
included (``config``)."""
from bayespd.linalg.config import (LinalgSettings, SuperLUFillError, choose_solver, current_settings,
                                   set_defaults, settings)

__all__ = ["LinalgSettings", "SuperLUFillError", "choose_solver", "current_settings", "set_defaults",
           "settings"]
