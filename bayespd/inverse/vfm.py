"""Peridynamic Virtual Fields Method (Delorme 2018): moduli from a measured
displacement field without any forward solve.

Principle of virtual work in PD (Delorme 2018 eqs 23-24, discretised as eq 30): for a virtual
field u* that vanishes on the constrained dofs (kinematically admissible, eq 29),

    W*_int + W*_ext = 0,   W*_int = sum_i sum_j f_v(x_j, x_i) . u*_i V_j V_i = -u*^T K u,
                           W*_ext = sum_i b_i . u*_i V_i = u*^T f,

where K is the linearised LPS stiffness of ``bayespd.materials`` (sum_j f_v V_j V_i is the
internal nodal force -(K u)_i) and f the scene's nodal loads. The extracted text of the paper
garbles eq 30; the form above is derived from eqs 21 and 24a and is what we use. Delorme 2018's
eq 31 evaluates W*_ext for a point load; here the same sum runs over the loaded particles.

Linearity (derived here, not stated in the paper): with the energy of ``materials/lps.py``,

    W_i = (a_s / 2) theta_i^2 + (a_d / (2 m_i)) sum_j w e_ij^2 V_j,
    a_s = kappa - c G / d^2,   a_d = c G    (c = 8 in 2D, 15 in 3D; kappa = in-plane bulk),

so K = a_s K_s + a_d K_d for homogeneous moduli, and W*_int is linear in the PD constants
(a_s, a_d) (Delorme 2018's alpha^d = 8G/q is a_d / m_i; its alpha^s, eqs 18-19/41, uses the 3D
split x theta / 3 of the extension and is another linear combination of the same two).
The residual of eq 25 is then minimised exactly by linear least squares over any number of
virtual fields (:func:`identify`); :func:`optimise` minimises it by Gauss-Newton with
autograd Jacobians for the general case (delta, influence parameters, surface correction).

The measured field is needed only where K u* is non-zero (W*_int = (K u*)^T u): within
about two horizons of where u* strains. Fields that are zero or rigid where data are missing
need no data there; :class:`VirtualWork` refuses fields that need missing data.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize
import torch


class ExactlyDeterminedWarning(UserWarning):
    """As many virtual fields as unknowns: the VFM residual is zero by construction."""


class PrescribedMismatchWarning(UserWarning):
    """Measured displacements on constrained dofs differ from the prescribed values."""


def pd_constants(material, K, G):
    """(a_s, a_d) = (kappa - c G / d^2, c G) of the module docstring, from bulk/shear moduli
    (c = ``material.c_d`` and kappa = ``material.kappa`` of the LPS material)."""
    K, G = torch.as_tensor(K), torch.as_tensor(G)
    c, d = material.c_d, material.dim
    return material.kappa(K, G) - c * G / d**2, c * G


def moduli_from_constants(material, a_s, a_d):
    """(K, G) from the PD constants; refuses constants that map to no positive K, G."""
    K, G = moduli_of_constants(material, np.asarray(a_s, dtype=float), np.asarray(a_d, dtype=float))
    if np.isnan(K):
        raise ValueError(f"the identified PD constants (a_s={float(a_s):.6g}, a_d={float(a_d):.6g}) "
                         "map to no positive (K, G): the virtual fields do not constrain the "
                         "moduli (add fields that strain the body where the data are good)")
    return float(K), float(G)


def moduli_of_constants(material, a_s: np.ndarray, a_d: np.ndarray) -> tuple:
    """(K, G) arrays from arrays of PD constants, NaN where they map to no positive K, G."""
    c, d = material.c_d, material.dim
    G = a_d / c
    kappa = a_s + a_d / d**2
    if material.dim == 3:
        K = kappa
    elif material.plane == "strain":
        K = kappa - G / 3
    else:  # plane stress: kappa = 9 K G / (3 K + 4 G)  =>  K = 4 G kappa / (9 G - 3 kappa)
        den = 9 * G - 3 * kappa
        K = np.where(den > 0, 4 * G * kappa / np.where(den > 0, den, 1.0), -1.0)
    ok = (G > 0) & (K > 0)
    return np.where(ok, K, np.nan), np.where(ok, G, np.nan)


PROBES = [(1.0, 1.0), (3.0, 1.0), (2.0, 3.0)]  # (K, G): two split K into K_s, K_d; one checks


def stiffness_times(material, params: dict, w: torch.Tensor) -> torch.Tensor:
    """K(params) w for fields w (M, N, dim), K assembled once (no autograd)."""
    A = material.pattern.matrix(material.numeric_stiffness(params))
    W = w.reshape(w.shape[0], -1).numpy().T  # (n_dofs, M)
    return torch.as_tensor(np.ascontiguousarray((A @ W).T)).reshape(w.shape)


def constant_parts(material, fixed: dict, w: torch.Tensor):
    """(K_s w, K_d w, [K(p) w for the PROBES]) for fields w (M, N, dim): K = a_s K_s + a_d K_d
    for homogeneous moduli, so two probe moduli give both parts; ``fixed`` holds delta and
    any other parameter of K."""
    Ku = [stiffness_times(material, dict(fixed, K=torch.tensor(K), G=torch.tensor(G)), w) for K, G in PROBES]
    C = torch.tensor([[float(c) for c in pd_constants(material, K, G)] for K, G in PROBES[:2]])
    Ps, Pd = (part.reshape(w.shape) for part in torch.linalg.solve(C, torch.stack(Ku[:2]).reshape(2, -1)))
    return Ps, Pd, Ku


def _describe(x, k):
    return f"particle {k} at {np.round(x[k], 6).tolist()}"


@dataclass
class VFMResult:
    params: dict                  # identified K, G (and any other estimated parameter)
    constants: tuple              # (a_s, a_d) at the estimate
    phi: float                    # Delorme 2018 eq 25 at the estimate
    residuals: list               # W*_int + W*_ext per virtual field (N mm)
    evaluations: int              # residual evaluations (0 for the closed form)
    wall_time_s: float
    method: str
    extra: dict = field(default_factory=dict)


def measured(x, u, observed=None):
    """(u as an (N, dim) array, the (N, dim) mask of its measured entries) for particles at
    ``x``: ``observed`` (N,) or (N, dim), default the finite entries; non-finite entries are
    never measured."""
    u = np.asarray(u.detach() if torch.is_tensor(u) else u, dtype=float)
    n, dim = x.shape
    if u.shape != (n, dim):
        raise ValueError(f"u must be (N, dim) = {(n, dim)} on the scene's particles, got {u.shape}")
    obs = np.isfinite(u) if observed is None else np.asarray(observed, dtype=bool)
    if obs.shape == (n,):
        obs = np.repeat(obs[:, None], dim, axis=1)
    if obs.shape != (n, dim):
        raise ValueError(f"observed must be a boolean mask of shape (N,) or (N, {dim})")
    return u, obs & np.isfinite(u)


class VirtualWork:
    """Virtual works of a scene's virtual fields (Delorme 2018 eqs 24, 30-31).

    ``scene``: a ``bayespd.Scene`` (its material, Dirichlet constraints and loads);
    ``fields``: callables u*(x) -> (N, dim) (see ``virtual_fields``); ``fixed``: the params
    that are not identified, at least ``{"delta": ...}``. Fields are evaluated at the
    particles and checked for kinematic admissibility (zero on every constrained dof, eq 29).
    The virtual internal-force fields K_s u*, K_d u* are precomputed, so the closed form costs
    two dot products per field for any measured field.
    """

    def __init__(self, scene, fields, fixed: dict, *, tol: float = 1e-9):
        if "delta" not in fixed:
            raise ValueError("fixed params need the horizon: fixed={'delta': ...}")
        self.scene, self.material = scene, scene.material
        if getattr(self.material, "c_d", None) is None:
            raise ValueError(f"the PD VFM identifies the state-based (LPS) moduli K and G, whose works "
                             f"are linear in (a_s, a_d); {type(self.material).__name__} has no "
                             "dilatation term: build the scene with bayespd.LPS")
        self.fixed = {k: torch.as_tensor(v) for k, v in fixed.items()}
        self.tol = tol
        p = self.material.particles
        self.x = p.x
        n, dim = p.n, p.dim
        if not isinstance(fields, (list, tuple)) or len(fields) == 0:
            raise ValueError("give a non-empty list of virtual fields (callables u*(x) -> (N, dim))")
        values = []
        for k, f in enumerate(fields):
            v = np.asarray(f(p.x), dtype=float)
            if v.shape != (n, dim):
                raise ValueError(f"virtual field {k} returned shape {v.shape}; it must map x (N, {dim}) "
                                 f"to (N, {dim})")
            if not np.all(np.isfinite(v)):
                raise ValueError(f"virtual field {k} is NaN or inf somewhere: fix the callable")
            if not np.any(v):
                raise ValueError(f"virtual field {k} is zero at every particle")
            values.append(v)
        self.ustar = torch.as_tensor(np.stack(values))  # (M, N, dim)
        self.fixed_dofs = ~scene.constraints.free_mask.reshape(n, dim)
        self._check_admissible()
        self.external = (self.ustar * scene.force).sum(dim=(1, 2))  # eq 24b / 31
        self._basis()

    @property
    def n_fields(self) -> int:
        return self.ustar.shape[0]

    def _check_admissible(self):
        for k, v in enumerate(self.ustar.numpy()):
            bad = self.fixed_dofs & (np.abs(v) > self.tol * np.abs(v).max())
            if bad.any():
                i, c = np.argwhere(bad)[0]
                raise ValueError(
                    f"virtual field {k} is not kinematically admissible: it is non-zero on "
                    f"{int(bad.sum())} constrained dof(s) (e.g. {_describe(self.x, i)}, component "
                    f"{c}, u* = {v[i, c]:.3g}), where the unknown reactions would do work "
                    "(Delorme 2018 eq 29). Make it vanish on every Dirichlet region, e.g. "
                    "virtual_fields.bending_fields(..., clear_half_width=, clear_depth=) for "
                    "support patches, or multiply it by a weight that is zero there "
                    "(virtual_fields.scaled)")

    def _basis(self):
        """K_s u*, K_d u* (``constant_parts``) and a third probe to check that K is linear
        in (a_s, a_d) (it is not e.g. with the surface correction)."""
        self.Ps, self.Pd, Ku = constant_parts(self.material, self.fixed, self.ustar)
        a_s, a_d = pd_constants(self.material, *PROBES[2])
        predicted = float(a_s) * self.Ps + float(a_d) * self.Pd
        scale = Ku[2].abs().max()
        self.linear = bool((predicted - Ku[2]).abs().max() <= 1e-9 * scale)
        size = sum(k.abs() for k in Ku)
        self.needed = (size > 1e-10 * size.amax(dim=(1, 2), keepdim=True)).numpy()  # (M, N, dim)

    def data(self, u, observed=None, sigma: float | None = None) -> torch.Tensor:
        """The measured field ready for the works: checks that every dof a field needs is
        known (observed, or prescribed by a Dirichlet region) and sets the rest to zero.

        Measured values are kept on the prescribed dofs too; the prescribed value fills only
        the prescribed dofs that are not measured. Replacing a measurement by the prescribed
        value would put a jump into the field wherever the data carry a rigid motion (FE and
        DIC fields do: grips slip, the camera's origin is arbitrary), and K u* reaches the
        constrained particles, so the jump would bias (K, G). With the measured field kept,
        W*_int = -(K u*)^T u is blind to rigid motion (K annihilates it). Where a measured
        value differs from the prescribed one by more than 4 ``sigma`` (the noise sd; without
        it, 1e-6 of the largest measured displacement) a :class:`PrescribedMismatchWarning`
        says so.

        ``u`` (N, dim) with NaN where not measured; ``observed`` an optional boolean mask (N,)
        or (N, dim) of the measured entries (default: the finite ones).
        """
        u, obs = self.measured(u, observed)
        prescribed = self.scene.constraints.prescribed.numpy()
        known = obs | self.fixed_dofs
        for k in range(self.n_fields):
            missing = self.needed[k] & ~known
            if missing.any():
                i = np.argwhere(missing)[0][0]
                raise ValueError(
                    f"virtual field {k} needs the displacement at {int(missing.any(1).sum())} "
                    f"particle(s) that are not observed (e.g. {_describe(self.x, i)}): W*_int "
                    "uses u wherever K u* != 0, i.e. within about two horizons of where u* "
                    "strains. Use a field that is zero (or rigid) there, e.g. "
                    "virtual_fields.scaled(field, weight) with a weight vanishing near the "
                    "missing data, or fill the data")
        self._check_prescribed(u, obs, prescribed, sigma)
        return torch.as_tensor(np.where(obs, u, np.where(self.fixed_dofs, prescribed, 0.0)))

    def measured(self, u, observed=None):
        """:func:`measured` at the scene's particles."""
        return measured(self.x, u, observed)

    def _check_prescribed(self, u, obs, prescribed, sigma):
        """Warn where measured constrained dofs disagree with their prescribed values."""
        both = obs & self.fixed_dofs
        if not both.any():
            return
        if sigma is not None and not (np.isfinite(sigma) and sigma >= 0):
            raise ValueError(f"sigma must be the noise sd (>= 0), got {sigma}")
        gap = np.where(both, np.abs(u - prescribed), 0.0)
        tol = 4 * sigma if sigma is not None else 1e-6 * np.abs(np.where(obs, u, 0.0)).max()
        if gap.max() > tol:
            i, c = np.unravel_index(np.argmax(gap), gap.shape)
            warnings.warn(
                f"the measured displacement differs from the prescribed one on {int((gap > tol).sum())} "
                f"constrained dof(s), by up to {gap.max():.3g} at {_describe(self.x, i)}, component {c} "
                f"(tolerance {tol:.3g}: " + ("4 sigma" if sigma is not None else "1e-6 max |u|; pass sigma=") +
                "). The measured values are used (the virtual works are blind to rigid motion); if the "
                "data carry no rigid motion, check where the scene's supports are",
                PrescribedMismatchWarning, stacklevel=3)

    def internal_matrix(self, u) -> torch.Tensor:
        """A (M, 2) with W*_int = A @ (a_s, a_d) for homogeneous moduli (closed form)."""
        if not self.linear:
            raise ValueError("this material's stiffness is not linear in (a_s, a_d) (surface "
                             "correction or moduli-dependent influence): use vfm.optimise")
        return -torch.stack([(self.Ps * u).sum(dim=(1, 2)), (self.Pd * u).sum(dim=(1, 2))], dim=1)

    def internal(self, u, params: dict) -> torch.Tensor:
        """W*_int per field (eq 30) for any params (scalars or fields, delta included),
        differentiable in the params: -u*_k . K(params) u."""
        params = dict(self.fixed, **params)
        v = torch.zeros_like(u, requires_grad=True)
        Ku = torch.autograd.grad(self.material.form(params, v, u), v, create_graph=True)[0]
        return -(self.ustar * Ku).sum(dim=(1, 2))

    def residual(self, u, params: dict) -> torch.Tensor:
        """W*_int + W*_ext per field (the terms of eq 25)."""
        return self.internal(u, params) + self.external

    def phi(self, residuals) -> float:
        """Delorme 2018 eq 25: sqrt(sum_k r_k^2 / sum_k (W*_ext^(k))^2)."""
        r = torch.as_tensor(residuals)
        return float(torch.sqrt((r**2).sum() / (self.external**2).sum()))

    def _refuse_no_external_work(self):
        if float((self.external**2).sum()) == 0.0:
            raise ValueError("no virtual field does work on the loads (sum W*_ext^2 = 0): eq 25 "
                             "is undefined and only the ratio of the moduli is identifiable; "
                             "include a field that moves the loaded particles")


def system(work: VirtualWork, u, observed=None, sigma: float | None = None):
    """(A, b) with W*_int = A a and b = -W*_ext (A a = b at the true a), after the checks of
    the closed form: loads do work, rank 2, and a warning when exactly determined."""
    work._refuse_no_external_work()
    A = work.internal_matrix(work.data(u, observed, sigma)).numpy()
    scale = np.abs(A).max(axis=0)
    if work.n_fields < 2 or np.linalg.matrix_rank(A / scale, tol=1e-12) < 2:
        raise ValueError("need at least two independent virtual fields to identify (K, G): "
                         f"got {work.n_fields} giving a rank-{np.linalg.matrix_rank(A / scale, tol=1e-12)} system")
    if work.n_fields == 2:
        warnings.warn("two virtual fields for two unknowns: the system is exactly determined, so "
                      "Phi = 0 whatever the model error and the residual says nothing about the "
                      "fit; add fields (e.g. virtual_fields.interior_bumps, or "
                      "vfm_defaults.estimate's defaults)", ExactlyDeterminedWarning, stacklevel=3)
    return A, -work.external.numpy()


def least_squares_constants(A, b) -> np.ndarray:
    """argmin_a |A a - b| with the columns scaled to unit max (a_s and a_d differ by decades)."""
    scale = np.abs(A).max(axis=0)
    return np.linalg.lstsq(A / scale, b, rcond=None)[0] / scale


def identify(work: VirtualWork, u, *, observed=None, sigma: float | None = None) -> VFMResult:
    """Closed-form PD-VFM: least squares over the virtual fields of W*_int(a) = -W*_ext,
    i.e. the exact minimiser of Delorme 2018's eq 25 over (a_s, a_d), mapped to (K, G)
    (``observed``, ``sigma``: see :meth:`VirtualWork.data`; for noisy data with a known
    sigma, ``vfm_noise.weighted_identify`` is unbiased and gives standard errors)."""
    start = time.perf_counter()
    A, b = system(work, u, observed, sigma)
    a = least_squares_constants(A, b)
    K, G = moduli_from_constants(work.material, a[0], a[1])
    r = A @ a - b
    return VFMResult({"K": K, "G": G}, (float(a[0]), float(a[1])), work.phi(r), r.tolist(), 0,
                     time.perf_counter() - start, "closed_form")


def optimise(work: VirtualWork, u, init: dict, *, observed=None, sigma: float | None = None,
             bounds: dict | None = None, tol: float = 1e-15, max_evaluations: int = 200) -> VFMResult:
    """Minimise eq 25 over the params named in ``init`` (positive, on a log scale), e.g.
    K, G, and possibly delta or influence parameters, by Gauss-Newton (scipy least_squares,
    trust region) with Jacobians by autograd; the others come from ``work.fixed``."""
    start = time.perf_counter()
    work._refuse_no_external_work()
    names = list(init)
    if not names:
        raise ValueError("init must name at least one parameter to estimate")
    z0 = np.log([float(init[k]) for k in names])
    lo = [np.log(bounds[k][0]) if bounds and k in bounds else -np.inf for k in names]
    hi = [np.log(bounds[k][1]) if bounds and k in bounds else np.inf for k in names]
    ud = work.data(u, observed, sigma)
    norm = float(torch.sqrt((work.external**2).sum()))
    evaluations = 0
    cache = {}

    def evaluate(z):
        nonlocal evaluations
        key = tuple(z)
        if key not in cache:
            evaluations += 1
            zt = torch.tensor(z, requires_grad=True)
            r = work.residual(ud, {k: torch.exp(zt[i]) for i, k in enumerate(names)}) / norm
            J = torch.stack([torch.autograd.grad(rk, zt, retain_graph=True)[0] for rk in r])
            cache.clear()
            cache[key] = (r.detach().numpy(), J.numpy())
        return cache[key]

    res = scipy.optimize.least_squares(lambda z: evaluate(z)[0], z0, jac=lambda z: evaluate(z)[1],
                                       bounds=(lo, hi), method="trf", x_scale="jac", xtol=tol,
                                       ftol=tol, gtol=tol, max_nfev=max_evaluations)
    est = {k: float(np.exp(res.x[i])) for i, k in enumerate(names)}
    r = res.fun * norm
    moduli = {k: est.get(k, float(work.fixed.get(k, np.nan))) for k in ("K", "G")}
    a = tuple(float(c) for c in pd_constants(work.material, moduli["K"], moduli["G"]))
    return VFMResult(est, a, work.phi(r), r.tolist(), evaluations, time.perf_counter() - start,
                     "gauss_newton", {"status": int(res.status), "message": str(res.message)})


def _sensitivities(scene, params: dict):
    """(the factor of K(params) on the free dofs, -d u/d(a_s, a_d) = K^-1 K_k u (n_free, 2))."""
    c = scene.constraints
    p = {k: torch.as_tensor(v) for k, v in params.items()}
    with torch.no_grad():
        factor = scene.factor(p)
        u = c.expand(torch.as_tensor(factor.solve(scene.free_load(p).numpy())))
        Ps, Pd, _ = constant_parts(scene.material, {k: v for k, v in p.items() if k not in ("K", "G")}, u[None])
        Kk = torch.stack([c.free(Ps[0]), c.free(Pd[0])], 1).numpy()  # K_s u, K_d u on the free dofs
    return factor, factor.solve(Kk)


def moduli_sensitivities(scene, params: dict) -> np.ndarray:
    """d u/d(K, G) on the free dofs (n_free, 2) of the homogeneous LPS scene, exact: d u/d a_k
    = -K^-1 K_k u and the chain rule through :func:`pd_constants`; one factorisation (e.g.
    the Fisher information J^T J / Sigma^2 of iid noise on the displacements)."""
    _, S = _sensitivities(scene, params)
    moduli = torch.tensor([float(params["K"]), float(params["G"])])
    da = torch.autograd.functional.jacobian(lambda m: torch.stack(pd_constants(scene.material, m[0], m[1])), moduli)
    return -S @ da.numpy()


def noise_optimal_fields(scene, params: dict) -> list:
    """The two virtual fields w_k = K^-1 K^-1 K_k u (k = s, d; K = K(params) on the free
    dofs, K_k = dK/da_k, u = K^-1 f) for which the VFM equations w_k^T (K(a) y - f) = 0 are
    the normal equations of least squares on the displacements y (derived here: d u/d a_k
    = -K^-1 K_k u, so J_k^T (y - u) = -w_k^T (K y - f)). Made at a consistent estimate,
    the closed form with them is a one-step estimator, efficient as the noise vanishes;
    remade at each new estimate it converges to the maximum-likelihood estimate under iid
    Gaussian noise at the free dofs (the noise-optimised special fields of Avril, Grédiac
    and Pierron 2004, for the PD model). Costs one factorisation and three solves; the
    fields vanish on the constrained dofs."""
    factor, S = _sensitivities(scene, params)
    w = torch.as_tensor(factor.solve(S))
    return [lambda x, w=scene.constraints.embed(w[:, k]).numpy(): w for k in range(2)]
