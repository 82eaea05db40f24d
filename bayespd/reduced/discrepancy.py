"""The Bayesian approximation-error model: a Gaussian term for the discretisation (or model-form)
error of a cheap model at the observation points (Kaipio & Somersalo 2007, "Statistical
inverse problems: discretization, model reduction and inverse crimes", J. Comput. Appl. Math.
198, 493-504; the "enhanced error model").

With an accurate reference model R (a finer PD scene, or the scikit-fem continuum peer) and the
cheap model M that is calibrated, the data are y = R(theta) + e = M(theta) + eps(theta) + e with
the approximation error eps(theta) = R(theta) - M(theta). Kaipio & Somersalo replace eps by a
Gaussian whose moments are estimated from prior draws theta_i, eps_i = R(theta_i) - M(theta_i):

    y | theta ~ N(M(theta) + mu(theta), Gamma_eps + sigma^2 I).

Here mu(theta) = mu (``dependence="constant"``: their model) or mu + B (phi(theta) - phi_bar)
with phi = log of every parameter (``"linear"``: the part of eps that the parameters explain,
fitted by least squares over the draws; Gamma_eps is then the residual covariance, smaller).
Gamma_eps = W W^T + diag(d) is stored low rank: W holds the leading principal components of
the residuals (rank chosen by explained variance), d the residual variance they leave (floored).
With ``relative=True`` the moments are those of eps / s(theta), s = rms of M(theta) (the error
relative to the displacement scale, which the moduli set), and the likelihood scales them back:
N(M + s mu, s^2 Gamma_eps + sigma^2 I).

**Prior- or posterior-informed.** The draws theta_i may come from the prior (``prior_draws``:
Kaipio & Somersalo's choice; cheap, estimated once for every data set, conservative: the term
averages the error over the whole prior, so where eps varies strongly with theta its covariance
is wide and the posterior with it too) or from a first posterior approximation of the data set
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

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch.distributions import constraints, transform_to

MIN_DOF = 10  # a variance estimated from fewer degrees of freedom has relative sd sqrt(2 / dof) > 45 %
DEPENDENCES = ("constant", "linear")


@dataclass(frozen=True)
class Discrepancy:
    """The approximation error eps = reference - model at the observation points as
    N(mu + B (phi(params) - phi_bar), W W^T + diag(d)); entries flattened point-major
    (point 0 x, point 0 y, point 1 x, ...).

    mean (points, dim): mu; factor (n, k): W; diag (n,): d; rms: root mean square of eps over
    the draws and entries; explained: the fraction of the residual variance in W W^T;
    slope (n, p), names (p,), centre (p,): B, the parameters of phi = log(params) and phi_bar
    (``None``/empty for a constant mean); points (points, dim') or None: where it was estimated;
    relative: the moments are of eps / rms(prediction) (``gaussian`` scales them back).
    """

    mean: torch.Tensor
    factor: torch.Tensor
    diag: torch.Tensor
    rms: float
    explained: float
    num_draws: int
    slope: torch.Tensor | None = None
    names: tuple = ()
    centre: torch.Tensor | None = None
    points: torch.Tensor | None = None
    relative: bool = False

    def __post_init__(self):
        n = self.mean.numel()
        if self.mean.ndim != 2 or self.factor.shape[0] != n or self.diag.shape != (n,):
            raise ValueError(f"mean must be (points, dim), factor (n, k) and diag (n,) with n = points * dim; "
                             f"got {tuple(self.mean.shape)}, {tuple(self.factor.shape)}, {tuple(self.diag.shape)}")
        if self.slope is not None and (self.slope.shape != (n, len(self.names))
                                       or self.centre is None or self.centre.shape != (len(self.names),)):
            raise ValueError("slope must be (n, p) with p = len(names) and centre (p,)")

    @property
    def rank(self) -> int:
        return self.factor.shape[1]

    @property
    def shape(self) -> tuple:
        return tuple(self.mean.shape)

    def shift(self, params: dict | None = None) -> torch.Tensor:
        """mu(params), shape (points, dim): the expected error at ``params``."""
        if self.slope is None:
            return self.mean
        if params is None:
            raise ValueError(f"this discrepancy's mean depends on {list(self.names)}: pass params")
        phi = torch.stack([torch.log(torch.as_tensor(params[k], dtype=self.mean.dtype)) for k in self.names])
        return self.mean + (self.slope @ (phi - self.centre)).reshape(self.mean.shape)

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


def prior_draws(priors: dict, num: int, seed: int, names: Sequence[str] | None = None) -> list[dict]:
    """``num`` parameter dicts drawn from ``priors`` (``{name: torch distribution}``, Pyro's
    included), only ``names`` if given, reproducibly from ``seed``."""
    names = list(priors) if names is None else list(names)
    missing = set(names) - set(priors)
    if missing:
        raise ValueError(f"no prior for {sorted(missing)} (priors given for {sorted(priors)})")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return [{k: priors[k].sample() for k in names} for _ in range(num)]


def _supports(names: Sequence[str], bounds: dict | None) -> list:
    """Per name its open support (low, high), default (0, inf), and the map of the real line onto
    it that Pyro's unconstrained space uses (exp for (low, inf), a scaled sigmoid for (low, high),
    identity for (-inf, inf))."""
    bounds = {} if bounds is None else dict(bounds)
    unknown = set(bounds) - set(names)
    if unknown:
        raise ValueError(f"bounds given for {sorted(unknown)}, which are not among the parameters {list(names)}")
    out = []
    for k in names:
        low, high = (float(v) for v in bounds.get(k, (0.0, math.inf)))
        if not low < high:
            raise ValueError(f"bounds of {k!r} must satisfy low < high, got ({low}, {high})")
        if low == -math.inf:
            support = constraints.real if high == math.inf else constraints.less_than(high)
        else:
            support = constraints.greater_than(low) if high == math.inf else constraints.interval(low, high)
        out.append((low, high, transform_to(support)))
    return out


def _unconstrained(names: Sequence[str], values: torch.Tensor, supports: list) -> torch.Tensor:
    """(draws, p) values mapped to the real line; values on or outside a support are refused."""
    columns = []
    for j, (k, (low, high, transform)) in enumerate(zip(names, supports)):
        inside = (values[:, j] > low) & (values[:, j] < high)
        if not bool(inside.all()):
            bad = values[:, j][~inside][:3].tolist()
            raise ValueError(f"{k} = {bad} lies on or outside its bounds ({low}, {high}): give bounds that hold "
                             "every draw inside (the prior's support, e.g. {'delta': (h, delta_max)})")
        columns.append(transform.inv(values[:, j]))
    return torch.stack(columns, 1)


def _gaussian(names: list, mean: torch.Tensor, covariance: torch.Tensor, supports: list, num: int, seed: int,
              inflate: float) -> list[dict]:
    """``num`` draws z ~ N(mean, inflate * covariance) on the real line, mapped onto the supports."""
    if not inflate > 0:
        raise ValueError(f"inflate must be > 0 (the factor on the covariance), got {inflate}")
    if num < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    p = len(names)
    if covariance.shape != (p, p):
        raise ValueError(f"covariance must be ({p}, {p}) for {names}, got {tuple(covariance.shape)}")
    if not torch.allclose(covariance, covariance.T, rtol=1e-10, atol=0):
        raise ValueError("covariance must be symmetric")
    variance = covariance.diagonal()
    spread = bool((variance > (1e-10 * mean.abs().clamp(min=1.0)).square()).all())  # above rounding
    if not spread or int(torch.linalg.cholesky_ex(covariance / (variance[:, None] * variance).sqrt()).info) != 0:
        raise ValueError(f"covariance of {names} is not positive definite: some combination of the parameters "
                         "has no spread (too few or identical draws, or a parameter held fixed)")
    gen = torch.Generator().manual_seed(seed)
    z = mean + math.sqrt(inflate) * torch.randn(num, p, generator=gen, dtype=torch.float64) @ torch.linalg.cholesky(
        covariance).T
    x = torch.stack([transform(z[:, j]) for j, (_, _, transform) in enumerate(supports)], 1)
    return [dict(zip(names, row)) for row in x]


def gaussian_draws(mean: dict, covariance, num: int, seed: int, *, inflate: float = 1.0,
                   bounds: dict | None = None) -> list[dict]:
    """``num`` parameter dicts from a Gaussian on the unconstrained space, e.g. a Laplace
    approximation: ``mean`` ``{name: value}`` (its centre, in the parameters' own units),
    ``covariance`` (p, p) of the unconstrained parameters (log(x - low) for (low, inf),
    logit((x - low) / (high - low)) for (low, high), as Pyro's; order of ``mean``), multiplied
    by ``inflate``; ``bounds`` ``{name: (low, high)}``, default (0, inf). Reproducible from ``seed``."""
    names = list(mean)
    supports = _supports(names, bounds)
    centre = torch.tensor([[float(mean[k]) for k in names]], dtype=torch.float64)
    z = _unconstrained(names, centre, supports)[0]
    return _gaussian(names, z, torch.as_tensor(covariance, dtype=torch.float64), supports, num, seed, inflate)


def _per_draw_scalar(array) -> bool:
    """One value per draw: a DataArray over (chain, draw) only, or a 1-D array."""
    dims = getattr(array, "dims", None)
    return tuple(dims) == ("chain", "draw") if dims is not None else np.ndim(array) == 1


def posterior_draws(tree, num: int, seed: int, *, names: Sequence[str] | None = None, inflate: float = 1.0,
                    bounds: dict | None = None) -> list[dict]:
    """``num`` parameter dicts from the Gaussian with the mean and covariance of a fitted
    posterior's draws on the unconstrained space (see ``gaussian_draws``), the covariance
    multiplied by ``inflate``: the draws of a posterior-informed error term (module docstring;
    Calvetti et al. 2018). ``tree``: a fit's DataTree (its ``posterior`` group, any chains) or a
    mapping ``{name: draws}``; ``names``: the parameters to draw (default: every scalar one);
    ``bounds`` ``{name: (low, high)}``, default (0, inf), e.g. the prior's support of delta."""
    posterior = tree["posterior"] if "posterior" in tree else tree
    names = [k for k in posterior if _per_draw_scalar(posterior[k])] if names is None else list(names)
    missing = [k for k in names if k not in posterior]
    if missing or not names:
        raise ValueError(f"no posterior draws of {missing or 'any scalar parameter'} (it holds {list(posterior)})")
    wrong = [k for k in names if not _per_draw_scalar(posterior[k])]
    if wrong:
        raise ValueError(f"{wrong} hold more than one value per draw: name scalar parameters only")
    columns = {k: torch.as_tensor(np.asarray(posterior[k]), dtype=torch.float64) for k in names}
    values = torch.stack([columns[k].reshape(-1) for k in names], 1)
    if len(values) < len(names) + 2:
        raise ValueError(f"{len(values)} posterior draws cannot give the covariance of {len(names)} parameters: "
                         f"give at least {len(names) + 2}")
    supports = _supports(names, bounds)
    z = _unconstrained(names, values, supports)
    return _gaussian(names, z.mean(0), torch.cov(z.T).reshape(len(names), len(names)), supports, num, seed,
                     inflate)


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


def _features(draws: Sequence[dict], names: tuple) -> torch.Tensor:
    values = torch.tensor([[float(p[k]) for k in names] for p in draws], dtype=torch.float64)
    if not bool((values > 0).all()):
        raise ValueError(f"dependence='linear' uses log(params) of {list(names)}: every drawn value must be positive")
    return values.log()


def estimate_discrepancy(reference: Callable, model: Callable, draws: Sequence[dict], rank: int | None = None, *,
                         explained: float = 0.99, dependence: str = "constant", relative: bool = False,
                         floor: float = 1e-6, points=None) -> Discrepancy:
    """The approximation-error term from ``draws`` of the prior or of a first posterior
    (``prior_draws``, ``posterior_draws``; Kaipio & Somersalo 2007, Calvetti et al. 2018).

    ``reference`` and ``model``: callables ``params -> (points, dim)`` observations, e.g.
    ``lambda p: fine.observe(fine.solve(p))``; each is called once per draw, in order.
    ``dependence``: ``"constant"`` (mean mu) or ``"linear"`` (mu + B (log params - mean) over
    every parameter the draws hold, B by least squares). ``relative``: model eps / rms(model(theta)) instead of eps (see the
    module). ``rank``: the number of principal components in W; by default the fewest
    that hold ``explained`` of the residual variance. d: the residual variance they leave,
    floored at ``floor`` times its mean. ``points``: the observation points, kept so that a
    model refuses a scene observed elsewhere. Needs ``MIN_DOF`` residual degrees of freedom:
    at least 11 draws (constant) or 11 + the number of parameters (linear).
    """
    if dependence not in DEPENDENCES:
        raise ValueError(f"dependence must be one of {DEPENDENCES}, not {dependence!r}")
    names = tuple(draws[0]) if (dependence == "linear" and draws) else ()
    columns = 1 + len(names)
    if len(draws) < columns + MIN_DOF:
        raise ValueError(f"{len(draws)} draws leave fewer than {MIN_DOF} degrees of freedom for the covariance "
                         f"(dependence={dependence!r} fits {columns} mean coefficients per entry): use at least "
                         f"{columns + MIN_DOF} draws (a few dozen is typical)")
    if not 0 < explained <= 1:
        raise ValueError(f"explained must lie in (0, 1], got {explained}")
    E, shape = _errors(reference, model, draws, relative)
    X = torch.ones(len(draws), 1, dtype=torch.float64)
    centre = None
    if names:
        phi = _features(draws, names)
        centre = phi.mean(0)
        X = torch.cat([X, phi - centre], dim=1)
    coef = torch.linalg.lstsq(X, E).solution  # (columns, n): row 0 mu, rows 1: B^T
    dof = len(draws) - columns
    R = (E - X @ coef) / math.sqrt(dof)
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
        mean=coef[0].reshape(shape), factor=W, diag=d, rms=float(E.square().mean().sqrt()),
        explained=float(variance[:rank].sum()) / total if total > 0 else 1.0, num_draws=len(draws),
        slope=coef[1:].T.contiguous() if names else None, names=names, centre=centre,
        points=None if points is None else torch.as_tensor(points, dtype=torch.float64).clone(), relative=relative)
