"""Tikhonov-regularised least squares with adjoint gradients (Turner 2015 eqs 12, 18-19).

    J(z) = 1/2 sum_obs mask (H u(p) - y)^2 / sigma^2 + sum_k psi_k/2 ||L_k (z_k - z_ref,k)||^2,

with p = exp(z): the unknowns are log-parameters, so positivity comes for free. Each unknown is
a scalar or a per-particle field (Turner 2015 eq 17: P = 121 values of mu(x) in §4.2). Turner 2015
eq 12 penalises psi/2 int k^2 (natural units, centred at zero); we centre the penalty at a
reference and apply it to log-parameters, so psi is dimensionless and L = "gradient"
(``bayespd.inverse.regularization``) penalises relative roughness of a field.

Gradient: one forward and one adjoint solve with the same factorisation (eqs 18-19), whatever
the number of unknowns. Hessian-vector products: double backward through the solve (the
adjoint is itself a differentiable solve), either the exact Hessian or the Gauss-Newton one
J_r^T J_r + psi L^T L (positive semi-definite).

Methods: "L-BFGS-B" (bounds), "Newton-CG" (Hessian-vector products, no bounds) and
"trust-constr" (Hessian-vector products and bounds).
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize
import torch

from bayespd.inverse.error_weights import ErrorWeights
from bayespd.inverse.regularization import regularization_operator
from bayespd.inverse.stopping import EXACT_FIT, Monitor, Stop, projected_gradient
from bayespd.validate import count, positive

METHODS = ("L-BFGS-B", "Newton-CG", "trust-constr")
REFRESH, REFRESHES = 1e-2, 3  # rerun when a discrepancy's frozen scale moved by > 1 %; at most 3 reruns


class ModelErrorWarning(UserWarning):
    """An unregularised, unweighted Tikhonov fit leaves a misfit well above the noise sd."""


@dataclass
class TikhonovResult:
    """Estimates (floats for scalars, numpy arrays for fields) and diagnostics.

    ``misfit_norm`` = ||mask (H u - y)|| and ``penalty_norm`` = ||L (z - z_ref)|| (summed over
    unknowns in quadrature) are the two axes of the L-curve; ``history`` is J per iteration
    (Turner 2015 figs 3 and 5)."""

    params: dict
    objective: float
    residual_rms: float
    iterations: int
    evaluations: int
    wall_time_s: float
    converged: bool
    message: str
    misfit_norm: float = math.nan
    penalty_norm: float = math.nan
    hessp_evaluations: int = 0
    history: list = field(default_factory=list)
    reason: str = ""  # why it stopped: the test that passed, or why none did
    chi2: float = math.nan  # the (whitened) misfit sum of squares / sigma^2, without the penalty


class _Unknowns:
    """Packs the named unknowns (scalars or per-particle fields) into one log-vector z."""

    def __init__(self, init: dict, n_particles: int):
        self.names, self.slices, self.field = list(init), {}, {}
        start = 0
        for k in self.names:
            size = self._size(k, init[k], n_particles)
            self.slices[k], self.field[k] = slice(start, start + size), np.ndim(_numpy(init[k])) == 1
            start += size
        self.n_particles, self.size = n_particles, start

    @staticmethod
    def _size(name, value, n):
        shape = np.shape(_numpy(value))
        if shape not in ((), (n,)):
            raise ValueError(f"{name} has shape {shape}: a parameter is a scalar or a field with "
                             f"one value per particle, shape ({n},)")
        return 1 if shape == () else n

    def log(self, values: dict, what: str) -> np.ndarray:
        """z from natural values (scalars broadcast over a field); refuses non-positive values."""
        z = np.empty(self.size)
        for k in self.names:
            self._size(k, values[k], self.n_particles)
            v = np.broadcast_to(_numpy(values[k]), (self.slices[k].stop - self.slices[k].start,))
            if not (np.all(np.isfinite(v)) and np.all(v > 0)):
                raise ValueError(f"the {what} of {k} must be finite and positive (unknowns are "
                                 "log-parameters)")
            z[self.slices[k]] = np.log(v)
        return z

    def params(self, z) -> dict:
        """Natural values: tensors of shape () or (N,) (numpy z gives floats and arrays)."""
        if isinstance(z, torch.Tensor):
            return {k: torch.exp(z[s]) if self.field[k] else torch.exp(z[s][0]) for k, s in self.slices.items()}
        return {k: np.exp(z[s]) if self.field[k] else float(np.exp(z[s][0])) for k, s in self.slices.items()}


def _numpy(v) -> np.ndarray:
    return v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else np.asarray(v, dtype=float)


def _per_unknown(value, names, what, default):
    """One value for every unknown, or a dict by unknown (``default`` where it has none)."""
    if isinstance(value, dict):
        extra = set(value) - set(names)
        if extra:
            raise ValueError(f"{what} names unknowns that are not estimated: {sorted(extra)}")
        return {k: value.get(k, default) for k in names}
    return dict.fromkeys(names, value)


class Objective:
    """J(z) of the module docstring on log-parameters z, its gradient (one forward and one
    adjoint solve) and Hessian-vector products; the arguments are those of :func:`tikhonov`."""

    def __init__(self, scene, y, init: dict, *, fixed=None, mask=None, sigma: float = 1.0, psi=0.0,
                 ref: dict | None = None, L=None, hessian: str = "exact", discrepancy=None):
        if hessian not in ("exact", "gauss-newton"):
            raise ValueError("hessian must be 'exact' or 'gauss-newton'")
        fixed = dict(fixed or {})
        if set(init) & set(fixed):
            raise ValueError("a parameter cannot be both estimated and fixed")
        if not init:
            raise ValueError("init is empty: name at least one parameter to estimate")
        if not (math.isfinite(sigma) and (sigma > 0 or (sigma == 0 and discrepancy is not None))):
            raise ValueError(f"sigma must be finite and positive (0 only with a discrepancy: noise-free data), got {sigma}")
        particles = scene.particles
        self.unknowns = unknowns = _Unknowns(init, particles.n)
        names = unknowns.names
        if ref is not None and set(ref) != set(names):
            raise ValueError(f"ref must give every estimated parameter {names}, got {sorted(ref)}")
        self.psi = _per_unknown(psi, names, "psi", 0.0)
        for k, v in self.psi.items():
            if v is None or not (math.isfinite(v) and v >= 0):
                raise ValueError(f"psi for {k} must be finite and >= 0, got {v}: psi weights the "
                                 "regularisation (0 switches it off)")
        specs = _per_unknown(L, names, "L", None)
        self.ops = {k: regularization_operator(specs[k], k, unknowns.slices[k].stop - unknowns.slices[k].start,
                                               particles) for k in names}
        self.z0 = unknowns.log(init, "starting value")
        self.z_ref = torch.as_tensor(unknowns.log(ref if ref is not None else init, "reference"))
        y = torch.as_tensor(y, dtype=torch.float64)
        if mask is None and scene.observation is not None:
            mask = scene.observation.mask
        w = torch.ones_like(y) if mask is None else torch.as_tensor(np.asarray(mask), dtype=y.dtype)
        if w.shape != y.shape:
            raise ValueError(f"mask must have the shape of y {tuple(y.shape)}, got {tuple(w.shape)}")
        if not bool(torch.all(torch.isfinite(y[w > 0]))):
            raise ValueError("observations contain NaN or inf where the mask is true: mask them out")
        self.y = torch.where(w > 0, y, torch.zeros(()))  # NaN * 0 is NaN: clear unobserved entries
        self.w, self.sigma, self.scene, self.fixed, self.hessian = w, sigma, scene, fixed, hessian
        self.evaluations = self.hessp_evaluations = 0
        self.last, self.weights = {}, None
        if discrepancy is not None:
            with torch.no_grad():
                params = self.params(torch.as_tensor(self.z0))
                self.weights = ErrorWeights(discrepancy, w > 0, sigma, self.predict(params), params)

    def params(self, zt: torch.Tensor) -> dict:
        return dict(self.fixed, **self.unknowns.params(zt))

    def predict(self, params: dict) -> torch.Tensor:
        """H u(params): the scene's ``predict`` (a ``Scene``, a ``bp.ReducedScene`` or ``bp.Held``)."""
        return self.scene.predict(params)

    def residual(self, zt: torch.Tensor) -> torch.Tensor:
        """mask (H u - y) / sigma at log-parameters zt, or with a discrepancy the whitened
        residual of ``error_weights`` (observed entries only)."""
        params = self.params(zt)
        if self.weights is not None:
            return self.weights(self.predict(params), params, self.y)
        return (self.predict(params) - self.y) * self.w / self.sigma

    def refresh(self, z: np.ndarray) -> float:
        """Refreeze the discrepancy's covariance at z; returns the relative change of its scale."""
        self.last = {}
        with torch.no_grad():
            params = self.params(torch.as_tensor(z))
            before = self.weights.scale
            self.weights.refresh(self.predict(params), params)
        return abs(self.weights.scale / before - 1)

    def penalty_terms(self, zt: torch.Tensor) -> dict:
        out = {}
        for k, s in self.unknowns.slices.items():
            d = zt[s] - self.z_ref[s]
            out[k] = d if self.ops[k] is None else self.ops[k] @ d
        return out

    def penalty(self, zt: torch.Tensor) -> torch.Tensor:
        return sum(0.5 * self.psi[k] * (t**2).sum() for k, t in self.penalty_terms(zt).items())

    def __call__(self, z: np.ndarray):
        """(J, grad J) at z: one factorisation, one forward and one adjoint solve (none when
        z is the point evaluated last)."""
        if np.array_equal(self.last.get("z"), z):
            return self.last["J"], self.last["g"]
        self.evaluations += 1
        zt = torch.tensor(z, requires_grad=True)
        J = 0.5 * (self.residual(zt) ** 2).sum() + self.penalty(zt)
        (g,) = torch.autograd.grad(J, zt)
        self.last = {"z": np.array(z, copy=True), "J": float(J.detach()), "g": g.numpy()}
        return self.last["J"], self.last["g"]

    def hessp(self, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        """H v, H the exact Hessian (double backward through the solve) or Gauss-Newton's."""
        self.hessp_evaluations += 1
        zt = torch.tensor(z, requires_grad=True)
        vt = torch.as_tensor(np.asarray(v, dtype=np.float64))
        if self.hessian == "exact":
            J = 0.5 * (self.residual(zt) ** 2).sum() + self.penalty(zt)
            (g,) = torch.autograd.grad(J, zt, create_graph=True)
            return torch.autograd.grad(g @ vt, zt)[0].numpy()
        # Gauss-Newton: J_r^T (J_r v) + (penalty Hessian) v; J_r v by the double-backward trick
        r = self.residual(zt)
        a = torch.zeros_like(r, requires_grad=True)
        (Jta,) = torch.autograd.grad(r, zt, grad_outputs=a, create_graph=True)
        (Jv,) = torch.autograd.grad(Jta @ vt, a, retain_graph=True)
        (JtJv,) = torch.autograd.grad(r, zt, grad_outputs=Jv)
        zp = torch.tensor(z, requires_grad=True)
        (gp,) = torch.autograd.grad(self.penalty(zp), zp, create_graph=True)
        return (JtJv + torch.autograd.grad(gp @ vt, zp)[0]).numpy()


def tikhonov(scene, y, init: dict, *, fixed: dict | None = None, mask=None, sigma: float = 1.0,
             psi=0.0, ref: dict | None = None, bounds: dict | None = None,
             gtol: float = 1e-12, ftol: float = 1e-10, maxiter: int = 500, maxfun: int = 2000,
             stall: int = 20, L=None, method: str = "L-BFGS-B", hessian: str = "exact",
             discrepancy=None) -> TikhonovResult:
    """Estimate the parameters named in ``init`` (starting values) from observations ``y``.

    ``init`` values are scalars or per-particle arrays of shape (N,). ``fixed`` holds the
    parameters kept constant (e.g. ``{"delta": 3.0}``, or a known field), ``bounds`` optional
    (low, high) per parameter in natural units, ``ref`` the regularisation centre (defaults
    to ``init``), ``psi`` >= 0 a scalar or one per parameter, ``L`` the regularisation
    operator: None/"identity", "gradient" (fields) or a matrix, or a dict per parameter.
    ``mask`` (default: the observation's own) marks observed entries; data outside it may be NaN.
    ``method`` is one of METHODS; ``hessian`` ("exact" or "gauss-newton") is used by the
    Hessian-based methods.

    ``discrepancy`` (a ``bayespd.Discrepancy``, the approximation-error term of the scene against
    an accurate reference at the observation's points): the misfit becomes the generalised least
    squares of ``bayespd.inverse.error_weights`` (the term's mean added to the prediction, the
    residual weighted by (term covariance + sigma^2 I)^-1, sigma then the noise sd), its
    covariance frozen at the start's scale and refreshed at the estimate (up to REFRESHES reruns
    while it moves by more than REFRESH). **Use it for measured (DIC, FE) data**: the plain
    misfit lets the model's error (the PD surface effect, the supports) bias the weakly
    identified parameters; on scikit-fem fields of a beam in bending the plain LPS misses nu by
    30-57 % and the weighted misfit by < 2 % (docs/results.md, from FE field).

    Stopping (``bayespd.inverse.stopping``; scale-free: the optimiser minimises
    J / (J(init) gtol), so that its own gradient test at 1 is ours and no absolute threshold
    inside it, e.g. Newton-CG's curvature floor, acts before ours):
    ``gtol`` bounds the projected gradient of J / J(init) in log-parameters, ``ftol`` the
    relative decrease of J per iteration, ``maxiter`` the iterations, ``maxfun`` the
    evaluations of J; ``stall`` evaluations in a row without a relative decrease above
    ``ftol`` end a stalled run. ``converged`` is true only if the gradient, decrease or
    exact-fit test passed; ``reason`` says which, or why the run stopped without converging.
    The default ftol = 1e-10 is above J's round-off (~1e-13 relative, which the old default sat
    on: whether a noisy fit then converged or its line search got lost depended on the CPU) and
    far below what moves the answer: near the minimum J - J* = (z - z*)^T H (z - z*) / 2 with
    J* ~ n / 2 and H ~ n / sd^2, so a decrease of 1e-10 J* is a step of ~1e-5 sd in z.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    positive("gtol", gtol, "a tolerance on the projected gradient of J / J(init), e.g. 1e-12")
    positive("ftol", ftol, "a tolerance on the relative decrease of J per iteration, e.g. 1e-10")
    count("maxiter", maxiter, 1, "allow at least one iteration")
    count("maxfun", maxfun, 2, "allow at least two evaluations of J")
    count("stall", stall, 2, "a stall is at least two evaluations without progress, e.g. 20")
    f = Objective(scene, y, init, fixed=fixed, mask=mask, sigma=sigma, psi=psi, ref=ref, L=L,
                  hessian=hessian, discrepancy=discrepancy)
    unknowns = f.unknowns
    lo, hi = np.full(unknowns.size, -np.inf), np.full(unknowns.size, np.inf)
    for k, (low, high) in (bounds or {}).items():
        if k not in unknowns.slices:
            raise ValueError(f"bounds given for {k}, which is not estimated")
        if not 0 < low < high:
            raise ValueError(f"bounds for {k} must satisfy 0 < low < high, got ({low}, {high})")
        lo[unknowns.slices[k]], hi[unknowns.slices[k]] = np.log(low), np.log(high)
    bounded = bool(np.isfinite(lo).any() or np.isfinite(hi).any())
    if method == "Newton-CG" and bounded:
        raise ValueError("Newton-CG takes no bounds: use method='trust-constr' or 'L-BFGS-B'")
    z, history, wall, iterations, first_J0 = np.clip(f.z0, lo, hi), [], 0.0, 0, None
    for _ in range(1 + REFRESHES):
        z, J, converged, reason, message, its, hist, seconds, J0 = _minimise(
            f, z, lo, hi, method, gtol, ftol, maxiter, maxfun, stall)
        history, wall, iterations = history + hist, wall + seconds, iterations + its
        first_J0 = J0 if first_J0 is None else first_J0
        # an exact fit (to round-off of the first start) needs no refresh: its residual is 0 under
        # any covariance, and a rerun would start on J's round-off floor, where its tests mean nothing
        if f.weights is None or J <= EXACT_FIT * first_J0 or f.refresh(z) <= REFRESH:
            break
    else:
        J, converged = f(z)[0], False
        reason = f"the discrepancy's scale still moved by more than {REFRESH:.0%} after {REFRESHES} reruns"
    with torch.no_grad():
        zt = torch.as_tensor(z)
        params = f.params(zt)
        prediction = f.predict(params)
        r = (prediction - f.y) * f.w
        pen = math.sqrt(sum(float((t**2).sum()) for t in f.penalty_terms(zt).values()))
        chi2 = float(((r / sigma if f.weights is None else f.weights(prediction, params, f.y)) ** 2).sum())
    rms, n = float(torch.sqrt((r**2).sum() / f.w.sum())), float(f.w.sum())
    if f.weights is None and not any(f.psi.values()) and chi2 > n + 4 * math.sqrt(2 * n):
        warnings.warn(f"the misfit is {math.sqrt(chi2 / n):.3g} sigma rms (chi2 = {chi2:.4g} over {n:.0f} "
                      f"observations, > 4 sd above a chi2 of {n:.0f}): if sigma = {sigma:g} is the noise sd, the "
                      "model does not fit the data and its error biases the weakly informed parameters (nu in "
                      "bending: 30-57 % on FE fields). For measured data pass discrepancy= (an approximation-error "
                      "term, bp.estimate_discrepancy against an accurate reference)", ModelErrorWarning, stacklevel=2)
    return TikhonovResult(unknowns.params(z), J, rms, iterations, f.evaluations,
                          wall, converged, message, float(r.norm()), pen,
                          f.hessp_evaluations, history, reason, chi2)


def _minimise(f, z0, lo, hi, method, gtol, ftol, maxiter, maxfun, stall):
    """One run of the optimiser from z0 under the stopping rules of :func:`tikhonov`:
    (z, J, converged, reason, message, iterations, history, wall time, J at z0)."""
    bounded = bool(np.isfinite(lo).any() or np.isfinite(hi).any())
    J0 = f(z0)[0]
    scale = (J0 if J0 > 0 else 1.0) * gtol  # the optimisers' own gradient tests at 1 are ours
    monitor = Monitor(ftol, maxfun, stall)
    monitor.evaluated(z0, J0)
    history = []

    def scaled(z):
        monitor.proposed(z)
        J, g = f(z)
        monitor.evaluated(z, J)
        return J / scale, g / scale

    def callback(intermediate_result):
        z = intermediate_result.x
        history.append(f(z)[0])
        monitor.iteration(history[-1])

    options = {"L-BFGS-B": {"gtol": 1.0, "ftol": 0.0, "maxiter": maxiter, "maxfun": maxfun},
               "Newton-CG": {"xtol": 1e-14, "maxiter": maxiter},
               "trust-constr": {"gtol": 1.0, "xtol": 1e-14, "maxiter": maxiter}}[method]
    extra = {} if method == "L-BFGS-B" else {"hessp": lambda z, v: f.hessp(z, v) / scale}
    if bounded:
        extra["bounds"] = list(zip(lo, hi)) if method == "L-BFGS-B" else scipy.optimize.Bounds(lo, hi)
    start = time.perf_counter()
    try:
        res = scipy.optimize.minimize(scaled, z0, jac=True, method=method, callback=callback,
                                      options=options, **extra)
        z, message, stop = res.x, str(res.message), None
        iterations = int(res.nit)
    except Stop as s:
        z, message, stop, iterations = monitor.best_z, s.reason, s, len(history)
    wall = time.perf_counter() - start
    J, g = f(z)
    pg = projected_gradient(z, g * gtol / scale, lo, hi)
    if pg <= gtol:
        converged, reason = True, f"projected gradient {pg:.3g} <= gtol={gtol:g}"
    elif J <= EXACT_FIT * J0:
        converged, reason = True, (f"J fell to round-off of its start (J / J0 = {J / J0:.3g} <= {EXACT_FIT:g}): "
                                   "the data are fitted exactly")
    elif stop is not None:
        converged, reason = stop.converged, stop.reason
    elif iterations < maxiter and (("REDUCTION" in message and "FACTR" in message) or "precision loss" in message
                                   or (method == "Newton-CG" and "terminated successfully" in message)):
        converged = False  # scipy's own round-off stops: L-BFGS-B's test with ftol = 0 (an
        # iteration left J where it was), a line search lost in round-off or steps below xtol
        # = 1e-14 relative (Newton-CG)
        reason = (f"the optimiser stopped at J's round-off floor ({message}): projected gradient "
                  f"{pg:.3g} > gtol={gtol:g}; raise gtol or ftol")
    else:
        converged = False
        reason = (f"maxiter={maxiter} iterations spent" if iterations >= maxiter else
                  f"the optimiser stopped ({message}) with projected gradient {pg:.3g} > gtol={gtol:g}")
    return z, J, converged, reason, message, iterations, history, wall, J0
