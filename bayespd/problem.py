"""Scene: a material with its constraints, loads, observation and the optional parts a
problem declares (damage law, Brownian noise, confinement); solve(params) -> u, at(params) -> the
body at fixed params for the nonlinear solvers (``solvers.quasistatic``, ``solvers.fracture``)."""
from __future__ import annotations

import warnings
from functools import cached_property

import numpy as np
import torch

from bayespd.connectivity import floating_particles
from bayespd.linalg.config import STATIC_SOLVERS, choose_solver, refuse_superlu_fill
from bayespd.linalg.sparse import default_backend
from bayespd.linalg.stiffness_solver import Assembly
from bayespd.boundary import Constraints, Dirichlet, Load
from bayespd.materials.checks import NonFiniteParameterError
from bayespd.observe import LinearObservation
from bayespd.linalg.adjoint import ValuesForm, solve_form
from bayespd.solvers.noise import Covariance
from bayespd.solvers.body import LoadedBody
from bayespd.validate import finite

# Relative residual of the scene's iterative (PCG / AMG-PCG) solves: the adjoint gradient's
# error, ~ kappa * rtol relative, stays below the Taylor remainder's t^2 term at the steps a
# calibration takes (tests/test_problem.py: slope 2 for K, G, the load and delta at 1e-8, not
# at 1e-6); 1e-10 cost 23-25 instead of 19-20 AMG-PCG iterations at 160k particles.
SCENE_RTOL = 1e-8


class Scene:
    """A peridynamic problem built only from the parts it declares (shared/DESIGN.md, principle 1).

    The static solve is linear elastic: ``params`` holds the material's parameters
    (``material.param_names``, e.g. K, G and the horizon ``delta``) and an optional ``load``
    factor scaling every load. Each may be a tensor that requires grad: the gradient costs one
    extra solve with the same factor. The loads and Dirichlet values are those at load factor 1;
    a scene needs a load or a non-zero Dirichlet value (displacement control).

    Optional parts, used by the nonlinear solvers on ``at(params)``:

    * ``damage``: a law of ``bayespd.damage`` (Dodwell 2019 eq 2, You 2023 eq 3.10); without
      it ``quasi_static`` is nonlinear elasticity and allocates no damage state;
    * ``noise``: the Brownian forcing sqrt(2 C) dB of Dodwell 2019 eq 4, as a callable
      ``free_dofs -> Covariance`` (``bayespd.solvers.noise``), e.g. ``lambda dofs:
      white_noise(sigma, len(dofs))`` or ``lambda dofs: karhunen_loeve(x, sigma, length,
      dofs=dofs)``. A callable, not a covariance: C lives on the free dofs, which exist only
      once the scene has split off its Dirichlet dofs, and a Karhunen-Loeve C costs an
      eigendecomposition, paid only when a stochastic solver first asks (``covariance``);
    * ``eps`` >= 0: the confinement of Dodwell 2019 eq 3, (eps/2) sum_i u_i.u_i: the operator on
      the free dofs is A = K_ff + eps I (direct solver only).

    ``solver``: "auto" (default) picks a direct factorisation or the matrix-free PCG with
    algebraic multigrid ("amg") by size and installed backends (``bayespd.linalg.config``);
    "direct", "pcg" (bond-graph Laplacian factor, ``precondition_radius``) or "amg" force one.
    The chosen one is ``scene.solver``; iterative solves stop at a relative residual ``rtol`` (default ``SCENE_RTOL``).
    """

    def __init__(self, material, dirichlet: list[Dirichlet], loads: list[Load] = (),
                 observation: LinearObservation | None = None, *, damage=None, noise=None,
                 eps: float = 0.0, solver: str = "auto", precondition_radius: float | None = 1.5,
                 rtol: float = SCENE_RTOL):
        p = material.particles
        if not eps >= 0:
            raise ValueError(f"the confinement eps must be >= 0, got {eps}")
        finite("the confinement eps", eps, "pass a finite eps >= 0")
        if eps and solver not in ("direct", "auto"):
            raise ValueError("eps > 0 needs solver='direct'")
        self.eps = float(eps)
        if not dirichlet:
            raise ValueError("a static scene needs at least one Dirichlet region")
        delta_max = material.bonds.delta_max
        for bc in dirichlet:
            if bc.depth is not None and bc.depth < delta_max:
                warnings.warn(f"Dirichlet layer depth {bc.depth:g} < delta_max {delta_max:g}: "
                              "a layer thinner than the horizon under-constrains the nonlocal "
                              "boundary; constrain a layer at least one horizon thick", stacklevel=2)
        if noise is not None and not callable(noise):
            raise ValueError("noise must be a callable free_dofs -> Covariance, e.g. "
                             "lambda dofs: white_noise(sigma, len(dofs))")
        self.material, self.particles, self.observation = material, p, observation
        self.dirichlet, self.loads = list(dirichlet), list(loads)
        self.damage, self.noise = damage, noise
        if solver not in STATIC_SOLVERS:
            raise ValueError("solver must be 'auto' (by size, bayespd.linalg.config), 'direct' "
                             "(CHOLMOD/SuperLU), 'pcg' or 'amg' (matrix-free)")
        if solver == "auto":
            solver = choose_solver(p.n * p.dim, p.dim, default_backend(),
                                   needs_matrix=bool(eps) or not getattr(material, "matrix_free", True))
        self.solver, self.rtol = solver, rtol
        direct = solver == "direct"
        self.constraints = Constraints(p, material.pattern if direct else None, self.dirichlet)
        if not any(bool(load.force.ne(0).any()) for load in self.loads) and not self.constraints.has_prescribed:
            raise ValueError("a scene needs a Load or a Dirichlet region with a non-zero value "
                             "(displacement control): nothing loads this one")
        # PCG: K is never assembled; the preconditioner keeps the bonds with
        # |xi| <= precondition_radius * h (None: all bonds)
        self._assembly = None if direct else Assembly(material.grams(), self.constraints.free_mask)
        self._precondition_rows = None
        if solver == "pcg" and precondition_radius is not None:
            short = material.bonds.length <= precondition_radius * p.h * (1 + 1e-9)
            self._precondition_rows = {material.grams()[0]: short}
        _refuse_floating_pieces(material.bonds, self.constraints.fixed_particles)
        self.force = sum((load.nodal(p) for load in self.loads), torch.zeros(p.n, p.dim))
        _refuse_clamped_loads(self.loads, p, self.constraints.free_mask.reshape(p.n, p.dim))
        self.param_names = material.param_names

    def at(self, params: dict, loaded=None) -> LoadedBody:
        """The scene at fixed ``params`` with exact bond kinematics (``LoadedBody``), for
        ``quasi_static``, ``equilibrium`` and ``StochasticFracture``; ``loaded``: the particles
        whose reaction and mean displacement are recorded (default: the Dirichlet regions with
        a non-zero value, and the loaded regions)."""
        self._params(params)  # refuses missing or unknown names
        return LoadedBody(self, params, loaded)

    @cached_property
    def covariance(self) -> Covariance:
        """C of the Brownian forcing on the free dofs, built by ``noise`` on first use."""
        if self.noise is None:
            raise ValueError("this scene has no Brownian noise: declare it, e.g. Scene(..., "
                             "noise=lambda dofs: white_noise(sigma, len(dofs)))")
        free = self.constraints.free_dofs
        C = self.noise(free)
        if C.n != len(free):
            raise ValueError(f"the noise covariance must live on the {len(free)} free dofs it is "
                             "given (pass dofs=dofs to karhunen_loeve)")
        return C

    def _params(self, params: dict) -> dict:
        missing = set(self.param_names) - set(params)
        unknown = set(params) - set(self.param_names) - {"load"}
        if missing or unknown:
            raise ValueError(f"params need {list(self.param_names)} (+ optional 'load'); "
                             f"missing {sorted(missing)}, unknown {sorted(unknown)}")
        if "load" in params:
            finite("the load factor params['load']", params["load"], "pass a finite load factor",
                   NonFiniteParameterError)
        try:
            return {k: torch.as_tensor(v) for k, v in params.items()}
        except (TypeError, ValueError, RuntimeError) as error:
            bad = next(k for k, v in params.items() if not isinstance(v, (int, float, torch.Tensor, np.ndarray)))
            raise TypeError(f"params[{bad!r}] must be a number or a tensor of numbers, got {params[bad]!r}") from error

    def _form(self, v_free, u_free, *theta):
        """v^T A u on the free dofs (A = K_ff + eps I), as a function of the parameters in
        param_names; for (n_free, k) columns, the sum of the k column forms."""
        q = dict(zip(self.param_names, theta))
        c = self.constraints
        if u_free.dim() == 1:
            form = self.material.form(q, c.embed(v_free), c.embed(u_free))
        elif self.solver == "direct":  # one differentiable assembly of K_ff for all columns
            form = ValuesForm(c.pattern)(v_free, u_free, self.stiffness_values(q))
        else:
            form = sum(self._form(v_free[:, j], u_free[:, j], *theta) for j in range(u_free.shape[1]))
        return form + self.eps * (v_free * u_free).sum() if self.eps else form

    def stiffness_values(self, params: dict) -> torch.Tensor:
        """Values of A = K_ff + eps I on ``constraints.pattern``, differentiable (direct solver)."""
        if self.solver != "direct":
            raise ValueError(f"stiffness_values needs the assembled K, but this scene is solved "
                             f"matrix-free (solver={self.solver!r}, chosen by size when 'auto'): "
                             "build it with Scene(..., solver='direct')")
        p = self._params(params)
        values = self.constraints.free_values(self.material.stiffness(p))
        return values + self.eps * self._diagonal if self.eps else values

    @cached_property
    def _diagonal(self) -> torch.Tensor:
        """Indicator of the diagonal entries of ``constraints.pattern``."""
        pattern = self.constraints.pattern
        d = torch.zeros(pattern.nnz)
        d[pattern.position(np.arange(pattern.n), np.arange(pattern.n))] = 1.0
        return d

    def _factor(self, p: dict):
        c, m = self.constraints, self.material
        with torch.no_grad():
            if self.solver == "direct":
                if default_backend() == "splu":
                    refuse_superlu_fill(c.pattern.nnz)
                values = c.free_values(m.numeric_stiffness(p))
                return c.pattern.factorize(values + self.eps * self._diagonal if self.eps else values)
            return self._assembly.factorize(m.terms(p), self.solver, rtol=self.rtol,
                                            precondition_rows=self._precondition_rows,
                                            positions=self.particles.x)

    def factor(self, params: dict):
        """The factorised free-dof operator at ``params`` (no autograd): ``.solve(b)`` for numpy
        b (n_free,) or (n_free, k), so several dependent solves share one factorisation."""
        return self._factor(self._params(params))

    def free_load(self, params: dict) -> torch.Tensor:
        """The right-hand side f_f - K_fc u_c on the free dofs (differentiable)."""
        p = self._params(params)
        c, m = self.constraints, self.material
        f = self.force * p["load"] if "load" in p else self.force
        rhs = c.free(f)
        if c.has_prescribed:  # K u_c as the gradient of the form (also under no_grad)
            v = torch.zeros_like(c.prescribed, requires_grad=True)
            differentiable = torch.is_grad_enabled()  # read before enable_grad overrides it
            with torch.enable_grad():
                Ku = torch.autograd.grad(m.form(p, v, c.prescribed), v,
                                         create_graph=differentiable)[0]
            rhs = rhs - c.free(Ku)
        return rhs

    def solve_free(self, params: dict, rhs: torch.Tensor) -> torch.Tensor:
        """A^-1 rhs on the free dofs for rhs (n_free,) or (n_free, k): one factorisation for
        all columns, differentiable (twice) in every param and in rhs."""
        p = self._params(params)
        n = len(self.constraints.free_dofs)
        if rhs.shape[0] != n:
            raise ValueError(f"rhs must have {n} rows (the free dofs), got {tuple(rhs.shape)}")
        return solve_form(self._form, self._factor(p), rhs, [p[k] for k in self.param_names])

    def solve(self, params: dict) -> torch.Tensor:
        """Displacement (N, dim) at equilibrium; differentiable (twice) in every param. Finite
        inputs whose displacement overflows float64 (|f| / K near 1e308) raise
        ``NonFiniteParameterError`` (a rejected proposal to the samplers), never return inf."""
        u = self.constraints.expand(self.solve_free(params, self.free_load(params)))
        if not bool(torch.isfinite(u.detach()).all()):
            raise NonFiniteParameterError(
                "the displacement overflowed to NaN or inf although every input is finite: the load, "
                "the load factor params['load'] or a Dirichlet value is too large for the moduli "
                "(|u| ~ |f| / K beyond 1e308); rescale the units")
        return u

    def observation_matrix(self) -> torch.Tensor:
        """H on the free dofs as a sparse COO (n_points * dim, n_free) tensor: the observed
        displacements (flattened point-major) are H u_free + (the prescribed dofs' part)."""
        if self.observation is None:
            raise ValueError("this scene has no observation operator")
        H = self.observation.matrix(self.particles.n)[:, self.constraints.free_dofs].tocoo()
        return torch.sparse_coo_tensor(np.stack([H.row, H.col]), H.data, H.shape,
                                       check_invariants=True).coalesce()

    def predict(self, params: dict) -> torch.Tensor:
        """The observations (points, dim) at equilibrium, differentiable (twice): what a
        likelihood compares with data (a ``bayespd.reduced.ReducedScene`` gives the same)."""
        return self.observe(self.solve(params))

    def observe(self, u: torch.Tensor) -> torch.Tensor:
        if self.observation is None:
            raise ValueError("this scene has no observation operator")
        return self.observation(u)


def _refuse_clamped_loads(loads, particles, free: np.ndarray) -> None:
    """A load whose force acts only on Dirichlet dofs does nothing (the support takes it):
    refuse it; warn when part of it does."""
    for k, load in enumerate(loads):
        force = load.force.detach().cpu().numpy()
        volume = np.where(load.mask, particles.volume, 0.0)
        lost = [(c, volume[~free[:, c]].sum() / volume.sum()) for c in np.flatnonzero(force)]
        if lost and all(share == 1 for _, share in lost):
            raise ValueError(f"load {k} acts only on Dirichlet-constrained dofs (its region lies in a "
                             "clamped layer), so the supports take it and it moves nothing: apply it "
                             "to free particles, e.g. the layer on the opposite side")
        for c, share in lost:
            if share > 0:
                warnings.warn(f"{share:.0%} of load {k}'s component {c} acts on Dirichlet-constrained "
                              "dofs and is taken by the supports: keep loaded and clamped regions apart",
                              stacklevel=3)


def _refuse_floating_pieces(bonds, fixed: np.ndarray) -> None:
    """Each connected piece of the bond graph (a body cut through by a pre-crack, an
    isolated particle) needs a Dirichlet region, else it floats and K is singular."""
    piece = floating_particles(bonds, None, fixed)
    if len(piece):
        raise ValueError(f"{len(piece)} particle(s) (e.g. {piece[0]}) form a piece with no "
                         "Dirichlet region: it can move as a rigid body (a crack through the "
                         "body or an isolated particle?); constrain it or remove it")
