"""A-posteriori estimate of the reduced model's observation error at one draw, from the
residual of the full equations and no factorisation at that draw (Cui, Marzouk & Willcox 2015
sec 3.3 use the residual the same way to decide where the reduced model may be trusted).

With u_r = V a the reduced solution, the error e = u - u_r solves A(theta) e = r, the residual
r = b(theta) - A(theta) u_r, assembled at theta in O(bonds). A few conjugate-gradient steps on
that system, preconditioned by one factor of A at a reference point (made once, reused for every
draw), give e, and H e is the observation error. With a PCG scene (large systems) the
reference "factor" is its preconditioner (a factor of the short-bond stiffness) instead. It is an estimate, not a bound: its
effectivity on held-out draws is in ``ReducedScene.report``.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from bayespd.reduced.affine import Terms


class ErrorEstimator:
    """``estimator(params)`` -> the estimated largest |observation error| of ``rom`` at params;
    ``reference``: the params of the preconditioning factor; CG stops at ``rtol`` relative change
    of the estimate or after ``max_steps``."""

    def __init__(self, rom, reference: dict, rtol: float = 0.05, max_steps: int = 30):
        self.rom, self.reference, self.rtol, self.max_steps = rom, reference, rtol, max_steps
        H = rom.scene.observation_matrix().coalesce()
        self.H = sp.csr_matrix((H.values().numpy(), H.indices().numpy()), shape=H.shape)
        self._precondition = None

    def __getstate__(self):
        """Pickled without the factor (it does not pickle): remade on first use."""
        return {**self.__dict__, "_precondition": None}

    def __call__(self, params: dict) -> float:
        scene = self.rom.scene
        c = scene.constraints
        if self._precondition is None:  # a PCG scene's factor: its preconditioner, not PCG itself
            factor = scene.factor(self.reference)
            self._precondition = getattr(factor, "precondition", factor.solve)
        q = {k: torch.as_tensor(float(params[k]), dtype=torch.float64) for k in scene.param_names}
        terms = Terms(scene.material, q)
        full = np.zeros(c.prescribed.numel())

        def A(v):  # K_ff v, matrix-free
            full[c.free_dofs] = v
            return terms.apply(full)[c.free_dofs]

        with torch.no_grad():
            u = self.rom.V @ self.rom.coefficients_of(q).numpy()
            r = scene.free_load(q).numpy() - A(u)
        return float(np.abs(self.H @ self._cg(A, r)).max())

    def _cg(self, A, r) -> np.ndarray:
        """Preconditioned CG on A e = r from e = 0 (A a function v -> A v)."""
        e = np.zeros_like(r)
        if not np.any(r):  # the reduced solution solves the full equations
            return e
        z = self._precondition(r)
        p, rz = z.copy(), float(r @ z)
        for _ in range(self.max_steps):
            Ap = A(p)
            alpha = rz / float(p @ Ap)
            step = alpha * p
            e += step
            if np.abs(self.H @ step).max() <= self.rtol * np.abs(self.H @ e).max():
                break
            r = r - alpha * Ap
            z = self._precondition(r)
            rz, rz_old = float(r @ z), rz
            p = z + (rz / rz_old) * p
        return e
