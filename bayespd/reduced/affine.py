"""The affine split of a scene's operator in its moduli (``Material.term_coefficients``):
K(theta) = sum_t Theta_t(moduli) A_t(delta), each A_t = B_t^T diag(w_t) B_t a Gram term,
projected on a basis without assembling K: V^T A_t V = (B_t V)^T diag(w_t) (B_t V)."""
from __future__ import annotations

import numpy as np
import torch


def check_reducible(scene) -> None:
    """Refuse what the affine split cannot represent, naming the fix."""
    material = scene.material
    if material.surface_correction:
        raise ValueError("the surface correction's bond factors depend on the moduli non-affinely: "
                         "build the reduced model on a material with surface_correction=False")
    extra = set(material.param_names) - set(material.moduli_names) - {"delta"}
    if extra:
        raise ValueError(f"influence-function parameters {sorted(extra)} are not reduced: use an "
                         "influence function without parameters")
    if scene.eps:
        raise ValueError("the confinement eps is not split into terms: build the reduced model "
                         "from a scene with eps=0")


def coefficients(material, params: dict) -> torch.Tensor:
    """Theta_t at the scalar moduli in ``params`` (a tensor of T values, differentiable)."""
    moduli = {k: torch.as_tensor(params[k], dtype=torch.float64) for k in material.moduli_names}
    for k, v in moduli.items():
        if v.dim() != 0:
            raise ValueError(f"the reduced model takes a homogeneous {k} (a scalar), got shape "
                             f"{tuple(v.shape)}: a field needs the full model")
    return torch.stack([torch.as_tensor(t, dtype=torch.float64) for t in material.term_coefficients(moduli)])


class Terms:
    """The Gram terms (B_t as a scipy CSR matrix, w_t) of K at ``params`` (no autograd);
    ``data`` keeps each B_t's entries, so that a projection can reuse B_t V where they are the
    same tensor as before (the bond directions do not depend on delta)."""

    def __init__(self, material, params: dict):
        with torch.no_grad():
            q = {k: torch.as_tensor(float(v), dtype=torch.float64) for k, v in params.items()}
            terms = material.terms(q)
        self.data = [d for _, d, _ in terms]
        self.terms = [(g.operator(d), np.broadcast_to(np.asarray(w), (g.shape[0],))) for g, d, w in terms]

    def apply(self, u: np.ndarray) -> np.ndarray:
        """K u for u over all dofs (flat, or (dofs, k))."""
        return sum(B.T @ (w.reshape(-1, *[1] * (u.ndim - 1)) * (B @ u)) for B, w in self.terms)

    def project(self, V: np.ndarray, u_c: np.ndarray, reuse: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(V^T A_t V) (T, R, R) and -V^T A_t u_c (T, R) for V (dofs, R) zero on the
        prescribed dofs and u_c the prescribed values (zero elsewhere); ``reuse``: a dict kept
        between calls with the same V, holding B_t V for entries that did not change."""
        blocks, loads = [], []
        reuse = {} if reuse is None else reuse
        for t, ((B, w), data) in enumerate(zip(self.terms, self.data)):
            if reuse.get(t, (None,))[0] is not data:
                reuse[t] = (data, B @ V)
            BV = reuse[t][1]
            blocks.append(BV.T @ (w[:, None] * BV))
            loads.append(-(BV.T @ (w * (B @ u_c))))
        return np.stack(blocks), np.stack(loads)
