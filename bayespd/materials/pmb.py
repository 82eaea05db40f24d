"""Bond-based prototype microelastic brittle material (PMB, Dodwell 2019 eqs 1-2): linearised
stiffness, damaged stiffness and exact-kinematics force.

W_i = 1/4 sum_j c omega s^2 |xi| V_j, calibrated on the continuum family so that an isotropic
expansion stores the classical energy: c = 18K / int omega r dV in 3D (= 18K/(pi delta^4) for
omega = 1), 3K / (pi t M_2) in plane stress (nu = 1/3, E = K; = 9K/(pi t delta^3)) and
24K / (5 pi t M_2) in plane strain (nu = 1/4, E = 3K/2; = 72K/(5 pi t delta^3)), with
M_2 = int_0^delta omega r^2 dr. Every bond carries the weight omega(|xi|, delta) * beta(delta)
(influence function times partial volume).

Exact kinematics (Dodwell 2019 eq 2, ``bayespd.nonlinear``): bond energy 1/2 c_b w_b mu_b s^2 |xi|
V_i V_j, c_b the mean micromodulus of the two ends, w_b = omega * beta from ``bond_weight``,
times the surface factor when switched on; mu_b the intact fraction. The force of a bond
depends on its own extension only (``pairwise``); damage scales its stiffness by mu_b.
"""
from __future__ import annotations

import math
from functools import cached_property

import torch

from bayespd import bond_loops
from bayespd.materials.base import Force, Material


class BondBased(Material):
    """Prototype microelastic brittle (PMB) bond-based material, linearised.

    Params: ``{"K": bulk, "delta": horizon}`` (K a scalar or per particle), plus the
    influence function's parameters if any; Poisson's ratio is fixed by the model (1/4 in 3D
    and plane strain, 1/3 in plane stress).
    """

    moduli_names = ("K",)
    pairwise = True

    def moment(self, k: int, params: dict) -> torch.Tensor:
        """int_0^delta omega(r) r^k dr, the moment the micromodulus is calibrated with."""
        return self.influence.moment(k, params["delta"], params)

    def micromodulus(self, K: torch.Tensor, params: dict) -> torch.Tensor:
        """c calibrated on the continuum family with this influence function."""
        if self.dim == 3:
            return 18 * K / (4 * math.pi * self.moment(3, params))
        coef = 3.0 if self.plane == "stress" else 24.0 / 5.0
        return coef * K / (math.pi * self.particles.thickness * self.moment(2, params))

    def bond_stiffness(self, moduli: dict, params: dict) -> torch.Tensor:
        """k_b = c_b w_b V_i V_j / |xi| per bond (before the surface factor and damage)."""
        c = self.micromodulus(moduli["K"], params)
        c_b = 0.5 * (c.index_select(0, self.i) + c.index_select(0, self.j))  # 3x faster than c[self.i]
        return c_b * self.bond_weight(params) * self._volumes_over_length

    @cached_property
    def _volumes_over_length(self) -> torch.Tensor:
        """V_i V_j / |xi| per bond (fixed by the particles)."""
        return self.volume.index_select(0, self.i) * self.volume.index_select(0, self.j) / self.length

    def term_coefficients(self, moduli):
        """(K,): the micromodulus, and with it every bond stiffness, is linear in K."""
        return [moduli["K"]]

    def energy_parts(self, moduli, params, u, factor=1.0):
        """(0, W_i) with W_i = 1/4 sum_j c omega beta s^2 |xi| V_j: half of each bond's
        energy to each end; every bond carries the correction ``factor``."""
        half = 0.25 * factor * self.bond_stiffness(moduli, params) * self.extension(u) ** 2
        per_node = torch.zeros(self.particles.n, dtype=half.dtype).index_add(0, self.i, half).index_add(0, self.j, half)
        return torch.zeros_like(per_node), per_node / self.volume

    def bulk_energy_parts(self, moduli, params, axis: int):
        """(0, W) for a unit uniaxial strain along ``axis`` at a particle with a complete
        lattice family: W = 1/4 c sum omega beta n_a^4 |xi| V."""
        r, n, cell = self.lattice_family
        w = self.lattice_weight(r, params)
        W = 0.25 * self.micromodulus(moduli["K"], params) * (w * n[:, axis] ** 4 * r).sum() * cell
        return torch.zeros_like(W), W

    def stiffness_terms(self, moduli, params, factor=1.0, intact=None):
        """K = B^T diag(k) B with k = F_b k_b (times mu_b with ``intact``)."""
        k = factor * self.bond_stiffness(moduli, params)
        return [(self.extension_gram, self.extension_data, k if intact is None else k * intact)]

    def nonlinear(self, kinematics, params, dtype=torch.float64):
        return PMBForce(kinematics, params, dtype)


class PMBForce(Force):
    """Bond-based PMB: t_b = k_b mu e_b with k_b = c_b w_b V_i V_j / |xi| (times the factor)."""

    def __init__(self, kin, params, dtype=torch.float64):
        super().__init__(kin, params, dtype)
        self.k = (self.factor * kin.material.bond_stiffness(self.moduli, params)).to(dtype)

    def force(self, u, intact=None, components=None):
        intact = self._intact(u, intact)
        if components is None and bond_loops.usable(u, self.k, intact):
            return bond_loops.pmb_force(u, self.kin.ends, *self.kin.geometry(u.dtype), self.k, intact)
        y, r, e = components or self.kin.components(u)
        k = self.k if intact is None else self.k * intact
        return self._scatter(y, k * e / r, u)

    def strain_energy(self, u, intact=None):
        intact = self._intact(u, intact)
        e = self.kin.components(u)[2]
        k = self.k if intact is None else self.k * intact
        return 0.5 * (k * e * e).sum()
