"""Scene: a material with its constraints, loads and observation; solve(params) -> u."""
from __future__ import annotations

import torch

from bayespd.boundary import Constraints, Dirichlet, Load
from bayespd.observe import Observation
from bayespd.sparse import solve


class Scene:
    """A static linear-elastic peridynamic problem built only from the parts it declares.

    ``params`` holds the material moduli (e.g. ``K``, ``G``), the horizon ``delta`` and an
    optional ``load`` factor scaling every load; each may require grad.
    """

    def __init__(self, material, dirichlet: list[Dirichlet], loads: list[Load],
                 observation: Observation | None = None):
        p = material.particles
        if not dirichlet:
            raise ValueError("a static scene needs at least one Dirichlet region")
        if not loads:
            raise ValueError("a scene needs at least one Load")
        delta_max = material.bonds.delta_max
        for bc in dirichlet:
            if bc.depth is not None and bc.depth < delta_max:
                raise ValueError(f"Dirichlet layer depth {bc.depth:g} < delta_max "
                                 f"{delta_max:g}: constrain a layer at least one horizon thick")
        self.material, self.particles, self.observation = material, p, observation
        self.constraints = Constraints(p, material.pattern, dirichlet)
        self.force = sum(load.nodal(p) for load in loads)

    def solve(self, params: dict) -> torch.Tensor:
        """Displacement (N, dim) at equilibrium; differentiable in every entry of params."""
        if "delta" not in params:
            raise ValueError("params must include the horizon 'delta'")
        values = self.material.stiffness(params, params["delta"])
        f = self.force * params.get("load", 1.0)
        values_f, rhs = self.constraints.reduce(values, f)
        return self.constraints.expand(solve(self.constraints.pattern, values_f, rhs))

    def observe(self, u: torch.Tensor) -> torch.Tensor:
        if self.observation is None:
            raise ValueError("this scene has no observation operator")
        return self.observation(u)
