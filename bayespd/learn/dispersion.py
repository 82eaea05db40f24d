"""The MD sheet's measured static dispersion: its compliance C(k) (2 x 2) at the wavevectors of the
sinusoidal loads (paper 004 eq 5.1), and a PD symbol's relative error against it (issue 28).

A linear, translation-invariant sheet answers a load at wavevector k with y_hat(k) = C(k) f_hat(k)
(PD: C = S(k)^-1, ``PeriodicSheet.symbol``). A load cos(k1 x1) cos(k2 x2) e_a excites the modes
(+-k1, +-k2); the loads a = x and a = y at one (n1, n2) give C's columns at (k1, k2), and at the
mirror mode (k1, -k2) they give M C M (M = diag(1, -1): the grid and the honeycomb are mirror
symmetric about both axes), which is averaged in. The PD-MD misfit is then one symmetric relative
compliance error per orbit {(+-k1, +-k2)},

    Delta = L^T C L - I,   S = L L^T   (0 when C = S^-1),

its off-diagonal entry only where n1 n2 != 0 (on the axes both vanish by the mirror symmetry).
These are the independent errors the data hold: a nodal likelihood counts each orbit's 2 N values
of each load.
"""
from __future__ import annotations

import numpy as np
import torch

from bayespd.linalg.sparse import NotPositiveDefiniteError


def measured_compliance(forces: torch.Tensor, y: torch.Tensor, n: int) -> tuple[np.ndarray, torch.Tensor, torch.Tensor]:
    """(modes (O, 2): the lattice indices (n1, n2 >= 0) of each orbit, C (O, 2, 2), off_diagonal (O,):
    n1 n2 != 0) from sinusoidal loads ``forces`` and zero-mean responses ``y`` (loads, n * n, 2),
    nodes x-major; each (n1, n2) needs its x and its y load."""
    f_hat = torch.fft.fft2(torch.as_tensor(forces).reshape(-1, n, n, 2), dim=(1, 2))
    y_hat = torch.fft.fft2(torch.as_tensor(y).reshape(-1, n, n, 2), dim=(1, 2))
    quadrant = f_hat[:, : n // 2 + 1, : n // 2 + 1].abs().pow(2)
    columns = {}
    for m in range(len(f_hat)):
        n1, n2, a = np.unravel_index(int(quadrant[m].argmax()), quadrant[m].shape)
        if (n1, n2) == (0, 0):
            raise ValueError(f"load {m} has no wave: measured_compliance needs the sinusoidal loads of eq 5.1")
        both = [(n1, n2), (n1, -n2 % n)] if n1 and n2 else [(n1, n2)]
        column = [(y_hat[m, i, j] / f_hat[m, i, j, a]).real for i, j in both]
        if len(column) == 2:  # the mirror mode's column of M C M, mapped back
            mirror = torch.tensor([1.0, -1.0], dtype=column[1].dtype)
            column = [(column[0] + mirror * mirror[a] * column[1]) / 2]
        columns.setdefault((int(n1), int(n2)), {})[int(a)] = column[0]
    missing = sorted(k for k, v in columns.items() if len(v) != 2)
    if missing:
        raise ValueError(f"the waves {missing} lack their x or y load: each (n1, n2) needs both (eq 5.1's set)")
    modes = np.array(sorted(columns))
    C = torch.stack([torch.stack([columns[tuple(k)][0], columns[tuple(k)][1]], -1) for k in modes])
    C = (C + C.transpose(-1, -2)) / 2  # a static compliance is symmetric (Maxwell-Betti)
    return modes, C, torch.as_tensor((modes[:, 0] > 0) & (modes[:, 1] > 0))


def relative_compliance_error(S: torch.Tensor, C: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(Delta = L^T C L - I (O, 2, 2), log det S (O,)) for symbols S (O, 2, 2), S = L L^T; a symbol
    that is not positive definite (an operator that is not solvable) raises NotPositiveDefiniteError."""
    L, info = torch.linalg.cholesky_ex(S)
    if bool((info > 0).any()):
        raise NotPositiveDefiniteError("the PD symbol is not positive definite at a measured wavevector: the "
                                       "kernel violates the solvability constraint (eq 4.4)")
    return L.transpose(-1, -2) @ C @ L - torch.eye(2, dtype=S.dtype), torch.logdet(S)


def shell_of(wavevectors, h: float, edges) -> torch.Tensor:
    """The shell (0 .. len(edges)) of each wavevector (..., 2) by |k| h against ``edges`` (positive,
    increasing)."""
    edges = np.asarray(edges, float)
    if edges.ndim != 1 or not np.all(np.diff(edges) > 0) or not np.all(edges > 0):
        raise ValueError(f"shell edges must be positive and increasing in |k| h, got {edges}")
    return torch.as_tensor(np.searchsorted(edges, np.linalg.norm(np.asarray(wavevectors), axis=-1) * h))


def error_field(S: torch.Tensor, forces: torch.Tensor, s: torch.Tensor, tau: float, n: int,
                generator: torch.Generator) -> torch.Tensor:
    """One draw of the model error u_md - u_pd (loads, n * n, 2) under ``forces`` (loads, n * n, 2):
    at each k != 0, L^-T Delta(k) L^-1 f_hat(k) with S (n * n - 1, 2, 2) the symbols at
    ``PeriodicSheet.wavevectors``, Delta(k) = Delta(-k) symmetric of entries N(0, s_k^2) (s_k^2 / 2
    off the diagonal; ``s`` (n * n - 1,)) plus one offset common to every k, sd tau (tau / sqrt 2)."""
    A = torch.randn(n * n, 2, 2, dtype=S.dtype, generator=generator)
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    flat, partner = (a * n + b).ravel(), ((-a % n) * n + (-b % n)).ravel()
    A = A[torch.as_tensor(np.minimum(flat, partner))][1:]  # one Delta for k and -k
    common = torch.randn(2, 2, dtype=S.dtype, generator=generator)
    A = s[:, None, None] * A + tau * common
    Delta = (A + A.transpose(-1, -2)) / 2  # the diagonal A's own, N(0, s^2); off it N(0, s^2 / 2)
    Linv = torch.linalg.inv(torch.linalg.cholesky(S)).to(torch.complex128)
    f_hat = torch.fft.fft2(torch.as_tensor(forces).reshape(-1, n, n, 2), dim=(1, 2)).reshape(len(forces), -1, 2)
    e_hat = torch.zeros_like(f_hat)
    e_hat[:, 1:] = torch.einsum("kba,kbc,kcd,mkd->mka", Linv, Delta.to(Linv.dtype), Linv, f_hat[:, 1:])
    return torch.fft.ifft2(e_hat.reshape(-1, n, n, 2), dim=(1, 2)).real.reshape(forces.shape)
