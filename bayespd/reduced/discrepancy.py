"""The Bayesian approximation-error model: a Gaussian term for the discretisation (or model-form)
error of a cheap model at the observation points (Kaipio & Somersalo 2007, "Statistical
inverse problems: discretization, model reduction and inverse crimes", J. Comput. Appl. Math.
198, 493-504; the "enhanced error model").

With an accurate reference model R (a finer PD scene, or the scikit-fem continuum peer) and the
cheap model M that is calibrated, the data are y = R(theta) + e = M(theta) + eps(theta) + e with
the approximation error eps(theta) = R(theta) - M(theta). Kaipio & Somersalo replace eps by a
Gaussian whose moments are estimated from prior draws theta_i, eps_i = R(theta_i) - M(theta_i):

    y | theta ~ N(M(theta) + mu(theta), Gamma_eps + sigma^2 I).

Here mu(theta) = mu (``dependence="constant"``: their model) or a trend fitted to the draws in
features phi(theta) (default: the log of every parameter; bayespd/reduced/trend.py): linear,
mu + B (phi - phi_bar) (``"linear"``), or a radial-basis interpolant (``"smooth"``), the part of
eps that the parameters explain; Gamma_eps is then the covariance of what is left (the
least-squares residuals, or the interpolant's leave-one-out errors), smaller. A smooth trend from
space-filling prior draws is the prior-informed model that stays accurate where eps is strongly
nonlinear in theta, estimated once for every data set.
Gamma_eps = W W^T + diag(d) is stored low rank: W holds the leading principal components of
the residuals (rank chosen by explained variance), d the residual variance they leave (floored).
With ``relative=True`` the moments are those of eps / s(theta), s = rms of M(theta) (the error
relative to the displacement scale, which the moduli set), and the likelihood scales them back:
N(M + s mu, s^2 Gamma_eps + sigma^2 I).

**Prior- or posterior-informed.** The draws theta_i may come from the prior (``prior_draws``:
Kaipio & Somersalo's choice; estimated once for every data set; with a constant or linear mean
the term averages the error over the whole prior, so where eps varies strongly with theta its
covariance is wide and the posterior with it too; a smooth trend removes that, at the price of
dozens of draws per feature) or from a first posterior approximation of the data set
at hand (``posterior_draws``: the posterior-informed / iterative approximation error of
Lipponen, Seppanen & Kaipio 2013, J. Electron. Imaging 22 023008, and Calvetti,
Dunlop, Somersalo & Stuart 2018, "Iterative updating of model error for Bayesian inversion",
Inverse Problems 34 025008): fit without the term (Laplace, NUTS), draw from that posterior with
its covariance inflated (x4 say, so that the draws also cover where the corrected posterior
moves), estimate the term from them, refit with it, and optionally repeat from the new
posterior. Costs one estimate per data set, gives narrower intervals, and is needed when the
error varies strongly with the parameters; with ``dependence="linear"`` the mean is then a local
linearisation of eps around the posterior.

**When it is needed.** Without it the model treats eps as zero; the posterior sd of a parameter
that n observations inform falls like sigma / sqrt(n) while a systematic error of rms r biases it
by up to about r in the same units, so the term matters once r / sigma is not small next to
1 / sqrt(n), and always once r is comparable to or larger than sigma. ``Discrepancy.rms`` is r
(over the draws and entries), ``noise_ratio(sigma)`` is r / sigma. The numerical core: no Pyro.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from .trend import LogFeatures, fit_linear, fit_smooth

MIN_DOF = 10  # a variance estimated from fewer degrees of freedom has relative sd sqrt(2 / dof) > 45 %
TRENDS = {"linear": fit_linear, "smooth": fit_smooth}
DEPENDENCES = ("constant", *TRENDS)


@dataclass(frozen=True)
class Discrepancy:
    """The approximation error eps = reference - model at the observation points as
    N(mu(params), W W^T + diag(d)); entries flattened point-major (point 0 x, point 0 y, ...).

    mean (points, dim): the mean error over the draws (mu itself for a constant trend);
    factor (n, k): W; diag (n,): d; rms: root mean square of eps over the draws and entries;
    explained: the fraction of the residual variance in W W^T; trend: ``None`` (mu = mean) or a
    ``LinearTrend`` / ``SmoothTrend`` (bayespd/reduced/trend.py), params -> mu (n,);
    points (points, dim') or None: where it was estimated; relative: the moments are of
    eps / rms(prediction) (``gaussian`` scales them back).
    """

    mean: torch.Tensor
    factor: torch.Tensor
    diag: torch.Tensor
    rms: float
    explained: float
    num_draws: int
    trend: Callable | None = None
    points: torch.Tensor | None = None
    relative: bool = False

    def __post_init__(self):
        n = self.mean.numel()
        if self.mean.ndim != 2 or self.factor.shape[0] != n or self.diag.shape != (n,):
            raise ValueError(f"mean must be (points, dim), factor (n, k) and diag (n,) with n = points * dim; "
                             f"got {tuple(self.mean.shape)}, {tuple(self.factor.shape)}, {tuple(self.diag.shape)}")

    @property
    def rank(self) -> int:
        return self.factor.shape[1]

    @property
    def shape(self) -> tuple:
        return tuple(self.mean.shape)

    def shift(self, params: dict | None = None) -> torch.Tensor:
        """mu(params), shape (points, dim): the expected error at ``params``."""
        if self.trend is None:
            return self.mean
        if params is None:
            raise ValueError("this discrepancy's mean depends on the parameters: pass params")
        return self.trend(params).reshape(self.mean.shape)

    def gaussian(self, prediction: torch.Tensor, params: dict | None = None) -> tuple:
        """(loc (points, dim), factor (n, k), diag (n,)) of the data less the noise:
        ``prediction + s mu(params)`` and s W, s^2 d, with s = rms(prediction) if ``relative``
        else 1; ``prediction`` is the cheap model's (points, dim) observation. The likelihood
        is N(vec loc, factor factor^T + diag(diag + sigma^2))."""
        self.check_shape(tuple(prediction.shape), "the model's prediction")
        s = prediction.square().mean().sqrt() if self.relative else 1.0
        return prediction + s * self.shift(params), s * self.factor, s**2 * self.diag

    def covariance(self) -> torch.Tensor:
        """Gamma_eps = W W^T + diag(d), dense (n, n): for checks and small problems."""
        return self.factor @ self.factor.T + torch.diag(self.diag)

    def with_errors(self, errors, spread: bool = False) -> "Discrepancy":
        """This term plus an independent zero-mean Gaussian component whose covariance is the
        second moment (1/m) E^T E of the m rows of ``errors`` (m, n), in this term's units
        (relative if ``relative``): e.g. the reference's own discretisation error, unknown in
        sign, from the reference on two meshes, E_i = R_h(theta_i) - R_2h(theta_i) (for a method
        of order p >= 1, |R_h - R| ~ |R_h - R_2h| / (2^p - 1) <= |R_h - R_2h|: a bound for the
        reference's error against any finer model). Appended to W as m columns E^T / sqrt(m).
        With ``spread`` the mean square of E is also added to every entry of d: the part of an
        error of that size whose shape the m rows do not span (a finer mesh's error is not
        exactly the coarser pair's), counted as independent entries."""
        errors = torch.as_tensor(errors, dtype=self.factor.dtype)
        if errors.ndim != 2 or errors.shape[1] != self.factor.shape[0] or len(errors) == 0:
            raise ValueError(f"errors must be (m >= 1, {self.factor.shape[0]}): one flattened (points, dim) error "
                             f"per row, entries point-major like the term's; got {tuple(errors.shape)}")
        if not bool(torch.isfinite(errors).all()):
            raise ValueError("errors hold NaN/inf: put 0 where an entry has no error (e.g. outside the body)")
        diag = self.diag + errors.square().mean() if spread else self.diag
        return dataclasses.replace(self, factor=torch.cat([self.factor, errors.T / math.sqrt(len(errors))], 1), diag=diag)

    def noise_ratio(self, sigma: float) -> float:
        """rms / sigma: the error's size next to the noise sd (see the module's "when it is needed")."""
        return self.rms / float(sigma)

    def check_shape(self, shape: tuple, what: str) -> None:
        if tuple(shape) != self.shape:
            raise ValueError(f"{what} has shape {tuple(shape)} but the discrepancy was estimated at "
                             f"{self.shape[0]} points x {self.shape[1]} components {self.shape}: estimate it "
                             "with reference and model observed at the data's points")

    def check_points(self, points) -> None:
        """Refuse observation ``points`` other than those the term was estimated at (when known)."""
        self.check_shape((len(points), self.shape[1]), "the scene's observation")
        if self.points is None:
            return
        points = torch.as_tensor(points, dtype=self.points.dtype)
        if points.shape != self.points.shape or not torch.allclose(points, self.points, rtol=0, atol=1e-9):
            raise ValueError("the discrepancy was estimated at other observation points than the scene's: "
                             "estimate it with reference and model observed at the data's points "
                             "(estimate_discrepancy(..., points=scene.observation.points))")


def _errors(reference: Callable, model: Callable, draws: Sequence[dict], relative: bool) -> tuple[torch.Tensor, tuple]:
    """eps_i = reference(draw_i) - model(draw_i) (divided by rms(model(draw_i)) if ``relative``),
    stacked (draws, points * dim), checked."""
    rows, shape = [], None
    with torch.no_grad():
        for i, params in enumerate(draws):
            r = torch.as_tensor(reference(params), dtype=torch.float64)
            m = torch.as_tensor(model(params), dtype=torch.float64)
            if r.shape != m.shape or r.ndim != 2:
                raise ValueError(f"the reference predicts shape {tuple(r.shape)} but the model {tuple(m.shape)}: "
                                 "both must observe the same (points, dim) entries, the data's; build each "
                                 "scene's Observation at the same points")
            if shape is not None and r.shape != shape:
                raise ValueError(f"draw {i} predicts shape {tuple(r.shape)}, earlier draws {tuple(shape)}")
            if not bool(torch.isfinite(r).all() and torch.isfinite(m).all()):
                which = "reference" if not bool(torch.isfinite(r).all()) else "model"
                raise ValueError(f"the {which} returned NaN/inf at draw {i} ({params}): "
                                 "draw parameters inside both scenes' range (delta between h and delta_max of each)")
            shape = r.shape
            rows.append((r - m).reshape(-1) / (m.square().mean().sqrt() if relative else 1.0))
    return torch.stack(rows), tuple(shape)


def estimate_discrepancy(reference: Callable, model: Callable, draws: Sequence[dict], rank: int | None = None, *,
                         explained: float = 0.99, dependence: str = "constant", features: Callable | None = None,
                         relative: bool = False, floor: float = 1e-6, points=None) -> Discrepancy:
    """The approximation-error term from ``draws`` of the prior or of a first posterior
    (``prior_draws``, ``posterior_draws``; Kaipio & Somersalo 2007, Calvetti et al. 2018).

    ``reference`` and ``model``: callables ``params -> (points, dim)`` observations, e.g.
    ``lambda p: fine.observe(fine.solve(p))``; each is called once per draw, in order.
    ``dependence``: ``"constant"`` (mean mu), ``"linear"`` (mu + B (phi - phi_bar), B by least
    squares) or ``"smooth"`` (a radial-basis interpolant of eps in phi, its covariance that of
    the leave-one-out errors: for errors far from linear in phi; dozens of draws per feature,
    space-filling over the region the posterior may reach), see bayespd/reduced/trend.py.
    ``features``: phi, a differentiable ``params -> 1-D tensor`` (picklable for NUTS worker
    processes), by default ``LogFeatures`` of every parameter the draws hold. ``relative``: model
    eps / rms(model(theta)) instead of eps (see the module); on a linear elastic scene under
    prescribed loads that relative error depends on the moduli only through their ratios, so
    features such as (log(G / K), delta) need fewer draws than (log K, log G, delta).
    ``rank``: the number of principal components in W; by default the fewest that hold
    ``explained`` of the residual variance. d: the residual variance they leave, floored at
    ``floor`` times its mean. ``points``: the observation points, kept so that a model refuses a
    scene observed elsewhere. Needs ``MIN_DOF`` residual degrees of freedom.
    """
    if dependence not in DEPENDENCES:
        raise ValueError(f"dependence must be one of {DEPENDENCES}, not {dependence!r}")
    if features is not None and dependence == "constant":
        raise ValueError("features are used by dependence='linear' or 'smooth' only: pass one of those")
    if not 0 < explained <= 1:
        raise ValueError(f"explained must lie in (0, 1], got {explained}")
    if len(draws) < 1 + MIN_DOF:
        raise ValueError(f"{len(draws)} draws leave fewer than {MIN_DOF} degrees of freedom for the covariance: "
                         f"use at least {1 + MIN_DOF} draws (a few dozen is typical)")
    E, shape = _errors(reference, model, draws, relative)
    if dependence == "constant":
        trend, residuals, dof = None, E - E.mean(0), len(draws) - 1
    else:
        trend, residuals, dof = TRENDS[dependence](features or LogFeatures(tuple(draws[0])), draws, E)
    if dof < MIN_DOF:
        raise ValueError(f"{len(draws)} draws leave {dof} < {MIN_DOF} degrees of freedom for the covariance once "
                         f"dependence={dependence!r} is fitted: use at least {len(draws) - dof + MIN_DOF} draws "
                         "(a few dozen is typical)")
    R = residuals / math.sqrt(dof)
    _, s, vt = torch.linalg.svd(R, full_matrices=False)
    variance = s.square()
    total = float(variance.sum())
    if rank is None:
        share = torch.cumsum(variance, 0) / total if total > 0 else torch.ones_like(variance)
        rank = int(torch.searchsorted(share, torch.tensor(explained * (1 - 1e-12)))) + 1
    if not 0 <= rank <= len(s):
        raise ValueError(f"rank must lie in 0..{len(s)} (at most the residual degrees of freedom), got {rank}")
    W = vt[:rank].T * s[:rank]
    per_entry = R.square().sum(0)
    d = (per_entry - W.square().sum(1)).clamp(min=floor * float(per_entry.mean()))
    return Discrepancy(
        mean=E.mean(0).reshape(shape), factor=W, diag=d, rms=float(E.square().mean().sqrt()),
        explained=float(variance[:rank].sum()) / total if total > 0 else 1.0, num_draws=len(draws), trend=trend,
        points=None if points is None else torch.as_tensor(points, dtype=torch.float64).clone(), relative=relative)
