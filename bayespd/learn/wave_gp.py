"""A Gaussian process over the wavevector for the relative compliance error Delta(k) of
``bayespd.learn.dispersion`` (issue 28): the model error at a wave without a training orbit,
drawn from its conditional given the training orbits' errors, so that its spread grows with the
distance to them (the shells of |k| h give every wave of a shell the same spread).

Each entry e of Delta (00, 11, 01; scale w_e = 1, 1, 1 / sqrt 2 as in models/md_dispersion.py) is

    Delta_e(k) = f_e(k) + eps_e(k),   f_e ~ GP(0, w_e^2 a^2 K_e),   eps_e ~ N(0, w_e^2 eta^2) white,

    K_e(k, k') = sum_{s1, s2 = +-1} sigma_e(s) exp(-|k h - (s1 k1', s2 k2') h|^2 / (2 l^2)),

sigma_e = 1 on the diagonal and s1 s2 off it: the mirror symmetry of the grid and the honeycomb
(Delta(k1, -k2) = M Delta(k) M, M = diag(1, -1)), so f_01 vanishes on the axes. A training orbit
is observed with the measurement error sigma_m on top (models/md_dispersion.py). a, l and eta
are fitted by the marginal likelihood of the training orbits' errors (``fit_wave_gp``); a
predicted record has fresh eps and its own measurement error.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from scipy.optimize import minimize

from bayespd.learn.dispersion import _ENTRY_SCALE, _symmetric

_MIRRORS = ((1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0))


class WaveGP(NamedTuple):
    """The GP's amplitude a, length scale l (in |k| h) and white sd eta (module docstring), with the
    sds of their logarithms at the marginal likelihood's maximum (Laplace; NaN where not fitted)."""

    amplitude: float
    length: float
    white: float
    log_sd: tuple[float, float, float] = (float("nan"),) * 3


def mirror_kernel(p: torch.Tensor, q: torch.Tensor, length, odd: bool) -> torch.Tensor:
    """K_e (P, Q) between the points ``p`` (P, 2) and ``q`` (Q, 2) in k h (module docstring;
    ``odd``: the off-diagonal entry's sign s1 s2)."""
    out = 0.0
    for s1, s2 in _MIRRORS:
        d = p[:, None, :] - q[None, :, :] * torch.tensor([s1, s2], dtype=q.dtype)
        out = out + (s1 * s2 if odd else 1.0) * torch.exp(-d.pow(2).sum(-1) / (2 * length**2))
    return out


def _entries(Delta: torch.Tensor, off):
    """(values, observed, odd, w) of entries 00, 11, 01 (01 only where ``off``)."""
    everywhere = torch.ones_like(off)
    return ((Delta[:, 0, 0], everywhere, False, _ENTRY_SCALE[0]), (Delta[:, 1, 1], everywhere, False, _ENTRY_SCALE[1]),
            (Delta[:, 0, 1], off, True, _ENTRY_SCALE[2]))


def _check(kh, Delta, off):
    kh, Delta = torch.as_tensor(kh, dtype=torch.float64), torch.as_tensor(Delta, dtype=torch.float64)
    off = torch.as_tensor(off, dtype=torch.bool)
    if kh.ndim != 2 or kh.shape[1] != 2 or Delta.shape != (len(kh), 2, 2) or off.shape != (len(kh),):
        raise ValueError(f"kh must be (O, 2) with Delta (O, 2, 2) and off_diagonal (O,), got {tuple(kh.shape)}, "
                         f"{tuple(Delta.shape)}, {tuple(off.shape)}")
    return kh, Delta, off


def log_marginal(log_theta: torch.Tensor, kh, Delta, off, measurement: float) -> torch.Tensor:
    """The training errors' log density (O orbits: ``kh`` (O, 2) = k h, ``Delta`` (O, 2, 2),
    ``off_diagonal`` (O,)) at log (a, l, eta), with the measurement sd ``measurement``."""
    a, length, eta = log_theta.exp()
    total = 0.0
    for value, held, odd, w in _entries(Delta, off):
        x = kh[held]
        cov = w**2 * (a**2 * mirror_kernel(x, x, length, odd) + (eta**2 + measurement**2) * torch.eye(len(x), dtype=x.dtype))
        total = total + torch.distributions.MultivariateNormal(torch.zeros_like(value[held]), cov).log_prob(value[held])
    return total


def fit_wave_gp(kh, Delta, off_diagonal, measurement: float, start: WaveGP = WaveGP(0.05, 0.5, 0.01)) -> WaveGP:
    """a, l, eta maximising ``log_marginal`` (L-BFGS on their logarithms, from ``start``) and the sds
    of their logarithms from the inverse Hessian there."""
    kh, Delta, off = _check(kh, Delta, off_diagonal)

    def objective(x):
        theta = torch.tensor(x, dtype=torch.float64, requires_grad=True)
        value = -log_marginal(theta, kh, Delta, off, measurement)
        value.backward()
        return float(value.detach()), theta.grad.numpy()

    x0 = np.log([start.amplitude, start.length, start.white])
    result = minimize(objective, x0, jac=True, method="L-BFGS-B", bounds=[(-12.0, 3.0)] * 3,
                      options={"maxiter": 500, "gtol": 1e-9})
    theta = torch.tensor(result.x, dtype=torch.float64)
    hessian = torch.autograd.functional.hessian(lambda t: -log_marginal(t, kh, Delta, off, measurement), theta)
    if not result.success or bool((torch.linalg.eigvalsh(hessian) <= 0).any()):
        raise ValueError(f"the GP's marginal likelihood has no interior maximum ({result.message}, Hessian "
                         f"{hessian.tolist()}): give the errors of more orbits or another start")
    a, length, eta = result.x
    sd = torch.linalg.inv(hessian).diagonal().sqrt().tolist()
    return WaveGP(float(np.exp(a)), float(np.exp(length)), float(np.exp(eta)), tuple(sd))


def conditional(gp: WaveGP, kh, Delta, off_diagonal, measurement: float, new) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per entry (00, 11, 01) the mean (P,) and covariance (P, P) of f_e at the points ``new`` (P, 2)
    in k h given the training errors (``kh`` (O, 2), ``Delta`` (O, 2, 2), ``off_diagonal`` (O,))."""
    kh, Delta, off = _check(kh, Delta, off_diagonal)
    new = torch.as_tensor(new, dtype=torch.float64)
    out = []
    for value, held, odd, w in _entries(Delta, off):
        x, scale = kh[held], w**2 * gp.amplitude**2
        cov = scale * mirror_kernel(x, x, gp.length, odd) + w**2 * (gp.white**2 + measurement**2) * torch.eye(len(x), dtype=x.dtype)
        cross = scale * mirror_kernel(new, x, gp.length, odd)
        L = torch.linalg.cholesky(cov)
        A = torch.cholesky_solve(torch.stack([value[held], *cross], -1), L)  # K^-1 [y, cross^T]
        out.append((cross @ A[:, 0], scale * mirror_kernel(new, new, gp.length, odd) - cross @ A[:, 1:]))
    return out


def draw_errors(gp: WaveGP, kh, Delta, off_diagonal, measurement: float, new, generator: torch.Generator,
                inflation: float = 1.0) -> torch.Tensor:
    """One draw (P, 2, 2) of a predicted record's model error f(k) + eps(k) at ``new`` (P, 2) in k h
    given the training errors (``conditional``, its deviation from the mean times ``inflation``,
    e.g. ``frame_extrapolation``'s); the off-diagonal f is 0 on the axes by the kernel."""
    entries = []
    for (mean, cov), w in zip(conditional(gp, kh, Delta, off_diagonal, measurement, new), _ENTRY_SCALE):
        value, vector = torch.linalg.eigh(cov)  # a root robust to the rounding of a near-singular covariance
        z = torch.randn(2, len(cov), dtype=cov.dtype, generator=generator)
        entries.append(mean + inflation * (vector @ (value.clamp(min=0).sqrt() * z[0]) + w * gp.white * z[1]))
    return _symmetric(entries)


def frame_extrapolation(modes, kh, Delta, off_diagonal, measurement: float) -> torch.Tensor:
    """The z-scores of the outermost frame of training orbits (max(n1, n2) = its largest, ``modes``
    (O, 2)) under the GP fitted to the inner ones alone: (Delta_e - mean) / sd of the predictive
    f + eps + measurement, every observed entry. Their rms is 1 where the GP extrapolates one
    lattice step as its law says; it measures how far the errors outgrow it from the data alone."""
    kh, Delta, off = _check(kh, Delta, off_diagonal)
    frame = torch.as_tensor(np.asarray(modes)).max(1).values
    inner, outer = frame < frame.max(), frame == frame.max()
    gp = fit_wave_gp(kh[inner], Delta[inner], off[inner], measurement)
    z = []
    for (mean, cov), (value, held, _, w) in zip(conditional(gp, kh[inner], Delta[inner], off[inner], measurement,
                                                            kh[outer]), _entries(Delta[outer], off[outer])):
        sd = (cov.diagonal() + w**2 * (gp.white**2 + measurement**2)).sqrt()
        z.append(((value - mean) / sd)[held])
    return torch.cat(z)
