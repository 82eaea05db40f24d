"""Scene: a material with its constraints, loads and observation; solve(params) -> u."""
from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components

from bayespd.stiffness_solver import Assembly
from bayespd.boundary import Constraints, Dirichlet, Load
from bayespd.observe import LinearObservation
from bayespd.sparse import solve_form


class Scene:
    """A static linear-elastic peridynamic problem built only from the parts it declares.

    ``params`` holds the material moduli (``material.param_names``, e.g. K and G), the
    horizon ``delta`` and an optional ``load`` factor scaling every load. Each may be a
    tensor that requires grad: the gradient costs one extra solve with the same factor.
    """

    def __init__(self, material, dirichlet: list[Dirichlet], loads: list[Load],
                 observation: LinearObservation | None = None, solver: str = "direct",
                 precondition_radius: float | None = 1.5, rtol: float = 1e-10):
        p = material.particles
        if not dirichlet:
            raise ValueError("a static scene needs at least one Dirichlet region")
        if not loads:
            raise ValueError("a scene needs at least one Load")
        delta_max = material.bonds.delta_max
        for bc in dirichlet:
            if bc.depth is not None and bc.depth < delta_max:
                warnings.warn(f"Dirichlet layer depth {bc.depth:g} < delta_max {delta_max:g}: "
                              "a layer thinner than the horizon under-constrains the nonlocal "
                              "boundary; constrain a layer at least one horizon thick", stacklevel=2)
        self.material, self.particles, self.observation = material, p, observation
        if solver not in ("direct", "pcg"):
            raise ValueError("solver must be 'direct' (CHOLMOD/SuperLU) or 'pcg' (matrix-free)")
        self.solver, self.rtol = solver, rtol
        direct = solver == "direct"
        self.constraints = Constraints(p, material.pattern if direct else None, dirichlet)
        # PCG: K is never assembled; the preconditioner keeps the bonds with
        # |xi| <= precondition_radius * h (None: all bonds)
        self._assembly = None if direct else Assembly(material._grams(), self.constraints.free_mask)
        self._precondition_rows = None
        if not direct and precondition_radius is not None:
            short = material.bonds.length <= precondition_radius * p.h * (1 + 1e-9)
            self._precondition_rows = {material._grams()[0]: short}
        _refuse_floating_pieces(material.bonds, self.constraints.fixed_particles)
        self.force = sum(load.nodal(p) for load in loads)
        self.param_names = (*material.param_names, "delta")

    def _params(self, params: dict) -> dict:
        missing = set(self.param_names) - set(params)
        unknown = set(params) - set(self.param_names) - {"load"}
        if missing or unknown:
            raise ValueError(f"params need {list(self.param_names)} (+ optional 'load'); "
                             f"missing {sorted(missing)}, unknown {sorted(unknown)}")
        return {k: torch.as_tensor(v) for k, v in params.items()}

    def _form(self, v_free, u_free, *theta):
        """v^T K_ff u on the free dofs, as a function of the parameters in param_names."""
        q = dict(zip(self.param_names, theta))
        c = self.constraints
        return self.material.form(q, q["delta"], c.embed(v_free), c.embed(u_free))

    def solve(self, params: dict) -> torch.Tensor:
        """Displacement (N, dim) at equilibrium; differentiable (twice) in every param."""
        p = self._params(params)
        c, m = self.constraints, self.material
        with torch.no_grad():
            if self.solver == "direct":
                factor = c.pattern.factorize(c.free_values(m.numeric_stiffness(p, p["delta"])))
            else:
                factor = self._assembly.factorize(m._terms(p, p["delta"]), "pcg", rtol=self.rtol,
                                                  precondition_rows=self._precondition_rows)
        f = self.force * p["load"] if "load" in p else self.force
        rhs = c.free(f)
        if c.has_prescribed:  # f_f - K_fc u_c, K u_c as the gradient of the form
            v = torch.zeros_like(c.prescribed, requires_grad=True)
            Ku = torch.autograd.grad(m.form(p, p["delta"], v, c.prescribed), v, create_graph=True)[0]
            rhs = rhs - c.free(Ku)
        u_free = solve_form(self._form, factor, rhs, [p[k] for k in self.param_names])
        return c.expand(u_free)

    def observe(self, u: torch.Tensor) -> torch.Tensor:
        if self.observation is None:
            raise ValueError("this scene has no observation operator")
        return self.observation(u)


def _refuse_floating_pieces(bonds, fixed: np.ndarray) -> None:
    """Each connected piece of the bond graph (a body cut through by a pre-crack, an
    isolated particle) needs a Dirichlet region, else it floats and K is singular."""
    n = len(fixed)
    graph = sp.coo_matrix((np.ones(bonds.n), (bonds.i, bonds.j)), shape=(n, n))
    count, label = connected_components(graph, directed=False)
    anchored = np.zeros(count, dtype=bool)
    anchored[label[fixed]] = True
    if not anchored.all():
        piece = np.flatnonzero(~anchored[label])
        raise ValueError(f"{len(piece)} particle(s) (e.g. {piece[0]}) form a piece with no "
                         "Dirichlet region: it can move as a rigid body (a crack through the "
                         "body or an isolated particle?); constrain it or remove it")
