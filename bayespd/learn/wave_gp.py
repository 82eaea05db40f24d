"""A Gaussian process over the wavevector for the relative compliance error Delta(k) of
``bayespd.learn.dispersion`` (issue 28): the model error at a wave without a training orbit,
drawn from its conditional given the training orbits' errors, so that its spread grows with the
distance to them (the shells of |k| h give every wave of a shell the same spread).

Each entry e of Delta (00, 11, 01; scale w_e = 1, 1, 1 / sqrt 2 as in models/md_dispersion.py) is

    Delta_e(k) = f_e(k) + eps_e(k),   f_e ~ GP(0, w_e^2 A(k) A(k') K_e),   eps_e ~ N(0, w_e^2 eta^2) white,

    K_e(k, k') = sum_{s1, s2 = +-1} sigma_e(s) exp(-|k h - (s1 k1', s2 k2') h|^2 / (2 l^2)),

    A(k)^2 = a^2 + g^2 (|k| h)^(2 p)   (g = 0: the stationary GP of amplitude a),

sigma_e = 1 on the diagonal and s1 s2 off it: the mirror symmetry of the grid and the honeycomb
(Delta(k1, -k2) = M Delta(k) M, M = diag(1, -1)), so f_01 vanishes on the axes; A depends on |k|
alone, so the product kernel keeps that symmetry and stays positive semi-definite (a Schur
product with the rank-one A A^T). The growing amplitude is the model error of a kernel fitted to
the long waves, which grows with |k| h (the outer training frame's errors are 2-3 times the inner
ones'). A training orbit is observed with the measurement error sigma_m on top
(models/md_dispersion.py). a, l, eta (and g, p) are fitted by the marginal likelihood of the
training orbits' errors (``fit_wave_gp``, which also returns that maximum, the evidence that
compares the two laws); a predicted record has fresh eps and its own measurement error.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from scipy.optimize import minimize

from bayespd.learn.dispersion import _ENTRY_SCALE, _symmetric

_MIRRORS = ((1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0))
_LOG_BOUNDS = ((-12.0, 3.0),) * 4 + ((-3.0, 3.0),)  # log a, l, eta, g; log p (p in 0.05-20)


class WaveGP(NamedTuple):
    """The GP's amplitude a, length scale l (in |k| h), white sd eta, growth g and power p (module
    docstring; g = 0: stationary), with the sds of the fitted ones' logarithms at the marginal
    likelihood's maximum (Laplace; empty where not fitted) and that maximum (NaN where not fitted)."""

    amplitude: float
    length: float
    white: float
    growth: float = 0.0
    power: float = 1.0
    log_sd: tuple[float, ...] = ()
    log_marginal: float = float("nan")


def mirror_kernel(p: torch.Tensor, q: torch.Tensor, length, odd: bool) -> torch.Tensor:
    """K_e (P, Q) between the points ``p`` (P, 2) and ``q`` (Q, 2) in k h (module docstring;
    ``odd``: the off-diagonal entry's sign s1 s2)."""
    out = 0.0
    for s1, s2 in _MIRRORS:
        d = p[:, None, :] - q[None, :, :] * torch.tensor([s1, s2], dtype=q.dtype)
        out = out + (s1 * s2 if odd else 1.0) * torch.exp(-d.pow(2).sum(-1) / (2 * length**2))
    return out


def envelope(gp: WaveGP, p: torch.Tensor) -> torch.Tensor:
    """A(k) (P,) at the points ``p`` (P, 2) in k h: sqrt(a^2 + g^2 (|k| h)^(2 p))."""
    return (gp.amplitude**2 + gp.growth**2 * p.pow(2).sum(-1).pow(gp.power)).sqrt()


def covariance(gp: WaveGP, p: torch.Tensor, q: torch.Tensor, odd: bool) -> torch.Tensor:
    """A(p) A(q) K_e(p, q) (P, Q): f_e's covariance less its entry scale w_e^2."""
    return envelope(gp, p)[:, None] * envelope(gp, q)[None, :] * mirror_kernel(p, q, gp.length, odd)


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


def _from_logs(log_hyper: torch.Tensor) -> WaveGP:
    """The GP of log (a, l, eta) (stationary) or log (a, l, eta, g, p) (growing)."""
    return WaveGP(*log_hyper.exp())


def log_marginal(log_hyper: torch.Tensor, kh, Delta, off, measurement: float) -> torch.Tensor:
    """The training errors' log density (O orbits: ``kh`` (O, 2) = k h, ``Delta`` (O, 2, 2),
    ``off_diagonal`` (O,)) at log (a, l, eta) or log (a, l, eta, g, p), with the measurement sd
    ``measurement``."""
    gp = _from_logs(log_hyper)
    total = 0.0
    for value, held, odd, w in _entries(Delta, off):
        x = kh[held]
        noise = (gp.white**2 + measurement**2) * torch.eye(len(x), dtype=x.dtype)
        cov = w**2 * (covariance(gp, x, x, odd) + noise)
        L = torch.linalg.cholesky(cov)
        r = torch.linalg.solve_triangular(L, value[held][:, None], upper=False)[:, 0]
        total = total - 0.5 * r.pow(2).sum() - L.diagonal().log().sum() - 0.5 * len(r) * np.log(2 * np.pi)
    return total


def fit_wave_gp(kh, Delta, off_diagonal, measurement: float, growing: bool = False,
                start: WaveGP = WaveGP(0.05, 0.5, 0.01, 0.02, 1.0)) -> WaveGP:
    """a, l, eta (``growing``: and g, p) maximising ``log_marginal`` (L-BFGS on their logarithms,
    from ``start``, within ``_LOG_BOUNDS``), the sds of their logarithms from the inverse Hessian
    there (NaN for one at its bound: eta -> 0 where the measurement error holds the white part),
    and the maximum."""
    kh, Delta, off = _check(kh, Delta, off_diagonal)
    count = 5 if growing else 3

    def objective(x):
        hyper = torch.tensor(x, dtype=torch.float64, requires_grad=True)
        value = -log_marginal(hyper, kh, Delta, off, measurement)
        value.backward()
        return float(value.detach()), hyper.grad.numpy()

    x0 = np.log(start[:count])
    result = minimize(objective, x0, jac=True, method="L-BFGS-B", bounds=_LOG_BOUNDS[:count],
                      options={"maxiter": 1000, "gtol": 1e-9})
    lower, upper = np.array(_LOG_BOUNDS[:count]).T
    free = (result.x > lower + 1e-6) & (result.x < upper - 1e-6)  # a bound is an answer (eta -> 0: no white term)
    step = 1e-4  # central differences of the exact gradient: a relative error of about step^2
    columns = [objective(result.x + step * e)[1] - objective(result.x - step * e)[1] for e in np.eye(count)[free]]
    hessian = torch.as_tensor(np.array(columns)[:, free] / (2 * step))
    hessian = (hessian + hessian.T) / 2
    if not result.success or bool((torch.linalg.eigvalsh(hessian) <= 0).any()):
        raise ValueError(f"the GP's marginal likelihood has no maximum ({result.message}, Hessian "
                         f"{hessian.tolist()}): give the errors of more orbits, another start, or a stationary GP "
                         f"(growing=False) where the errors do not grow with |k| h")
    sd = np.full(count, np.nan)
    sd[free] = torch.linalg.inv(hessian).diagonal().sqrt().numpy()
    return WaveGP(*np.exp(result.x).tolist(), log_sd=tuple(sd.tolist()), log_marginal=-float(result.fun))


def conditional(gp: WaveGP, kh, Delta, off_diagonal, measurement: float, new) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per entry (00, 11, 01) the mean (P,) and covariance (P, P) of f_e at the points ``new`` (P, 2)
    in k h given the training errors (``kh`` (O, 2), ``Delta`` (O, 2, 2), ``off_diagonal`` (O,))."""
    kh, Delta, off = _check(kh, Delta, off_diagonal)
    new = torch.as_tensor(new, dtype=torch.float64)
    out = []
    for value, held, odd, w in _entries(Delta, off):
        x = kh[held]
        cov = w**2 * (covariance(gp, x, x, odd) + (gp.white**2 + measurement**2) * torch.eye(len(x), dtype=x.dtype))
        cross = w**2 * covariance(gp, new, x, odd)
        L = torch.linalg.cholesky(cov)
        A = torch.cholesky_solve(torch.stack([value[held], *cross], -1), L)  # K^-1 [y, cross^T]
        out.append((cross @ A[:, 0], w**2 * covariance(gp, new, new, odd) - cross @ A[:, 1:]))
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


def frame_extrapolation(modes, kh, Delta, off_diagonal, measurement: float, growing: bool = False,
                        frame: int | None = None, gp: WaveGP | None = None) -> torch.Tensor:
    """The z-scores of the frame ``frame`` of training orbits (max(n1, n2) = ``frame``, default the
    largest; ``modes`` (O, 2)) under the GP conditioned on the orbits inside it alone, with the
    hyperparameters ``gp`` or (None) those fitted to those orbits (``growing`` as ``fit_wave_gp``):
    (Delta_e - mean) / sd of the predictive f + eps + measurement, every observed entry. Their rms
    is 1 where the GP extrapolates one lattice step as its law says; it measures how far the errors
    outgrow it from the data alone (a growth that only the outer frame shows needs ``gp`` fitted
    to every frame: the inner ones alone do not identify it)."""
    kh, Delta, off = _check(kh, Delta, off_diagonal)
    level = torch.as_tensor(np.asarray(modes)).max(1).values
    frame = int(level.max()) if frame is None else frame
    inner, outer = level < frame, level == frame
    if not bool(outer.any()):
        raise ValueError(f"no training orbit has max(n1, n2) = {frame}: pick a frame of the training set")
    gp = fit_wave_gp(kh[inner], Delta[inner], off[inner], measurement, growing) if gp is None else gp
    z = []
    for (mean, cov), (value, held, _, w) in zip(conditional(gp, kh[inner], Delta[inner], off[inner], measurement,
                                                            kh[outer]), _entries(Delta[outer], off[outer])):
        sd = (cov.diagonal() + w**2 * (gp.white**2 + measurement**2)).sqrt()
        z.append(((value - mean) / sd)[held])
    return torch.cat(z)
