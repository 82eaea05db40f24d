"""Linearised peridynamic materials: stiffness values on a fixed pattern, differentiable in
the moduli (scalars or per-particle fields) and the horizon delta.

LPS (ordinary state-based linear peridynamic solid, seed 000 eqs 5-10, seed 001 eqs 18-19,
35-45). With the dilatation theta_i = (d/m_i) sum_j w x e V_j, the deviatoric extension
e^d = e - theta x / d and alpha = c_d G / m (c_2 = 8, c_3 = 15), the energy density
W_i = kappa/2 theta^2 + alpha/2 sum_j w (e^d)^2 V_j rewrites, using sum_j w x e^d V_j = 0, as

    W_i = (kappa_i / 2 - c_d G_i / (2 d^2)) theta_i^2 + (c_d G_i / (2 m_i)) sum_j w e_ij^2 V_j,

so K = D^T diag(s) D + B^T diag(k_b) B (D maps u to dilatations, B to bond extensions;
see assembly.py) is the Hessian of sum_i V_i W_i: symmetric
even when the moduli vary from particle to particle (seed 000 eq 8). kappa is the in-plane
bulk modulus: 9KG/(3K+4G) in plane stress, K + G/3 in plane strain, K in 3D. This is the
2D split of Le et al. (2014) and equals seed 001's eqs 18-19 (which use the 3D split x theta/3
in 2D: expanding eq 45 with eq 41 gives the same coefficient 2(K + G/3)/q of theta x in plane
strain). Seed 000 prints k + mu/9 for that coefficient; the calibration above gives k + mu/3.

Bond-based PMB (seed 002 eq 1): W_i = 1/4 sum_j c omega s^2 |xi| V_j, calibrated on the
continuum family so that an isotropic expansion stores the classical energy:
c = 18K / int omega r dV in 3D (= 18K/(pi delta^4) for omega = 1), 3K / (pi t M_2) in plane
stress (nu = 1/3, E = K; = 9K/(pi t delta^3)) and 24K / (5 pi t M_2) in plane strain
(nu = 1/4, E = 3K/2; = 72K/(5 pi t delta^3)), with M_2 = int_0^delta omega r^2 dr.

Every bond carries the weight omega(|xi|, delta) * beta(delta) (influence function times
partial volume). LPS needs no recalibration for omega: m absorbs it.
"""
from __future__ import annotations

import math
from functools import cached_property

import numpy as np
import torch

from bayespd.linalg.assembly import Gram, numeric_values, union_pattern
from bayespd.bonds import Bonds, partial_volume
from bayespd.discretize import Particles
from bayespd.influence import Constant, Influence
from bayespd.surface import bond_factors

_C_DEV = {2: 8.0, 3: 15.0}


def moduli_from_young(E, nu):
    """Bulk and shear moduli (K, G) from Young's modulus and Poisson's ratio."""
    E, nu = torch.as_tensor(E), torch.as_tensor(nu)
    if not bool(torch.all(torch.isfinite(E)) and torch.all(E > 0)):
        raise ValueError("Young's modulus E must be finite and positive")
    if not bool(torch.all((nu > -1) & (nu < 0.5))):
        raise ValueError("Poisson's ratio must lie in (-1, 0.5): at nu = 0.5 (incompressible) "
                         "K = E / (3 (1 - 2 nu)) is infinite, and with it the plane-strain LPS "
                         "constant kappa = K + G/3, and above 0.5 K is negative; use nu < 0.5 "
                         "(e.g. 0.499: the condition number of K grows like 1 / (1 - 2 nu), "
                         "which a float64 direct solve handles)")
    return E / (3 * (1 - 2 * nu)), E / (2 * (1 + nu))


class ParameterRangeError(ValueError):
    """A modulus outside (0, inf): bad input, or a sampler's or optimiser's trial point that
    over- or underflowed (which the inference code treats as a rejected proposal)."""


class NonFiniteParameterError(ParameterRangeError):
    """A modulus is NaN or inf."""


def check_modulus(name: str, value, n: int) -> torch.Tensor:
    """A modulus as a tensor broadcastable to (n,); refuse NaN, inf and non-positive values."""
    v = torch.as_tensor(value)
    if v.dim() > 1 or (v.dim() == 1 and v.shape[0] != n):
        raise ValueError(f"{name} must be a scalar or have one value per particle ({n})")
    if not bool(torch.all(torch.isfinite(v))):
        raise NonFiniteParameterError(f"{name} contains NaN or inf: pass finite moduli")
    if not bool(torch.all(v > 0)):
        raise ParameterRangeError(f"{name} must be positive (got min {float(v.min()):g}): moduli "
                         "are positive; sample them on a log scale")
    return v


class _Material:
    """Shared machinery: a material is a list of Gram terms (operator, data, weights).

    ``influence`` weights the bonds (default constant); ``surface_correction=True`` scales
    each bond's stiffness by energy-based directional factors (see ``bayespd.surface``).
    """

    moduli_names: tuple[str, ...] = ()

    def __init__(self, particles: Particles, bonds: Bonds, plane: str = "stress",
                 influence: Influence | None = None, surface_correction: bool = False):
        if plane not in ("stress", "strain"):
            raise ValueError("plane must be 'stress' or 'strain'")
        self.particles, self.bonds, self.plane = particles, bonds, plane
        self.influence = influence or Constant()
        self.surface_correction = surface_correction
        self.param_names = (*self.moduli_names, *self.influence.param_names)
        self.dim = d = particles.dim
        self.volume = torch.as_tensor(particles.volume)
        self.length = torch.as_tensor(bonds.length)
        self.unit = torch.as_tensor(bonds.xi / bonds.length[:, None])
        self._i, self._j = torch.as_tensor(bonds.i), torch.as_tensor(bonds.j)
        # B: bond extensions e_b = n . (u_j - u_i); entries (b, d*i+a) = -n_a, (b, d*j+a) = n_a
        a = np.arange(d)
        rows = np.repeat(np.arange(bonds.n), 2 * d)
        cols = np.concatenate([d * bonds.i[:, None] + a, d * bonds.j[:, None] + a], axis=1).reshape(-1)
        self._extension = Gram(rows, cols, bonds.n, d * particles.n)
        self._extension_data = torch.cat([-self.unit, self.unit], dim=1).reshape(-1)

    def _grams(self) -> list[Gram]:
        return [self._extension]

    @cached_property
    def pattern(self):
        return union_pattern(self._grams())

    def bond_weight(self, params: dict, delta) -> torch.Tensor:
        """omega(|xi|, delta) * beta(delta) per bond; refuses particles left without a family."""
        w = self.influence(self.length, delta, params) * self.bonds.weight(delta)
        V = self.volume
        family = torch.zeros(self.particles.n, dtype=w.dtype).index_add(
            0, self._i, w.abs() * V[self._j]).index_add(0, self._j, w.abs() * V[self._i])
        if bool(torch.any(family == 0)):
            k = int(torch.nonzero(family == 0)[0])
            raise ValueError(f"particle {k} at {self.particles.x[k].tolist()} has an empty family "
                             "at this horizon: increase delta or remove isolated particles")
        return w

    @cached_property
    def _lattice_family(self):
        """Offsets of a complete family on the regular lattice of spacing h, up to delta_max
        + h/2: (lengths, units, cell volume), the bulk reference of the surface correction."""
        h, d = self.bonds.h, self.dim
        k = np.arange(-math.ceil(self.bonds.delta_max / h) - 1, math.ceil(self.bonds.delta_max / h) + 2)
        xi = h * np.stack(np.meshgrid(*[k] * d, indexing="ij"), axis=-1).reshape(-1, d)
        r = np.linalg.norm(xi, axis=1)
        keep = (r > 0) & (r < self.bonds.delta_max + h / 2)
        cell = h**d * (self.particles.thickness if d == 2 else 1.0)
        return torch.as_tensor(r[keep]), torch.as_tensor(xi[keep] / r[keep, None]), cell

    def _moduli(self, params: dict) -> dict:
        missing = set(self.param_names) - set(params)
        if missing:
            raise ValueError(f"{type(self).__name__} needs params {sorted(missing)} "
                             f"(has {list(self.param_names)})")
        n = self.particles.n
        return {k: check_modulus(k, params[k], n).expand(n) for k in self.moduli_names}

    def _bond_correction(self, moduli: dict, params: dict, delta):
        """Surface-correction factor per bond, or 1 when the correction is off."""
        return bond_factors(self, moduli, params, delta) if self.surface_correction else 1.0

    def _terms(self, params: dict, delta):
        moduli = self._moduli(params)
        return self._stiffness_terms(moduli, params, delta, self._bond_correction(moduli, params, delta))

    def energy_density(self, params: dict, delta, u: torch.Tensor) -> torch.Tensor:
        """W_i per particle for u of shape (N, dim) (surface-corrected when switched on)."""
        moduli = self._moduli(params)
        return sum(self._energy_parts(moduli, params, delta, u, self._bond_correction(moduli, params, delta)))

    def stiffness(self, params: dict, delta) -> torch.Tensor:
        """Values of K(params, delta) on ``self.pattern``, differentiable (twice)."""
        return sum(g.values(d, w, self.pattern) for g, d, w in self._terms(params, delta))

    def numeric_stiffness(self, params: dict, delta) -> torch.Tensor:
        """The same values assembled by scipy (no autograd graph; for factorisation)."""
        with torch.no_grad():
            return numeric_values(self.pattern, self._terms(params, delta))

    def form(self, params: dict, delta, v: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """v^T K(params, delta) u matrix-free: sum_t sum_r w_r (A_t v)_r (A_t u)_r."""
        v, u = v.reshape(-1), u.reshape(-1)
        return sum((w * g.apply(d, v) * g.apply(d, u)).sum() for g, d, w in self._terms(params, delta))

    def energy(self, params: dict, delta, u: torch.Tensor) -> torch.Tensor:
        """Total strain energy sum_i V_i W_i = u^T K u / 2 of the linearised model."""
        return 0.5 * self.form(params, delta, u, u)

    def extension(self, u: torch.Tensor) -> torch.Tensor:
        """Linearised bond extension e = n . (u_j - u_i) for u of shape (N, dim)."""
        return self._extension.apply(self._extension_data, u.reshape(-1))


class LPS(_Material):
    """Linear peridynamic solid (state-based), 2D plane stress / plane strain or 3D.

    Params: ``{"K": bulk, "G": shear}`` (3D moduli; scalars or per-particle tensors), plus
    the influence function's parameters if it has any.
    """

    moduli_names = ("K", "G")

    def __init__(self, particles: Particles, bonds: Bonds, plane: str = "stress",
                 influence: Influence | None = None, surface_correction: bool = False):
        super().__init__(particles, bonds, plane, influence, surface_correction)
        n, d, nb = particles.n, self.dim, bonds.n
        # family ends: one per bond touching a particle, then one self end per particle
        self._owner = torch.as_tensor(np.concatenate([bonds.i, bonds.j]))
        self._end_node = torch.as_tensor(np.concatenate([bonds.j, bonds.i]))
        self._end_bond = torch.as_tensor(np.concatenate([np.arange(nb), np.arange(nb)]))
        self._end_sign = torch.cat([torch.ones(nb), -torch.ones(nb)])
        self._end_volume = self.volume[self._end_node]
        owner = np.concatenate([bonds.i, bonds.j, np.arange(n)])
        node = np.concatenate([bonds.j, bonds.i, np.arange(n)])
        # D: dilatations theta_i = sum_e g_e . u_node(e)
        a = np.arange(d)
        self._dilatation = Gram(np.repeat(owner, d), (d * node[:, None] + a).reshape(-1), n, d * n)

    def _grams(self) -> list[Gram]:
        return [self._extension, self._dilatation]

    def kappa(self, K: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
        """In-plane bulk modulus of the dimension-reduced continuum."""
        if self.dim == 3:
            return K
        return 9 * K * G / (3 * K + 4 * G) if self.plane == "stress" else K + G / 3

    def _family_sum(self, per_end: torch.Tensor) -> torch.Tensor:
        return torch.zeros(self.particles.n, dtype=per_end.dtype).index_add(0, self._owner, per_end)

    def weighted_volume(self, w: torch.Tensor) -> torch.Tensor:
        """m_i = sum_j omega beta |xi|^2 V_j (seed 000 eq 9) for bond weights w."""
        m = self._family_sum(w[self._end_bond] * self.length[self._end_bond] ** 2 * self._end_volume)
        if bool(torch.any(m <= 0)):
            raise ValueError("a particle has a non-positive weighted volume m: the influence "
                             "function must be non-negative on average over each family")
        return m

    def _dilatation_vectors(self, w, m):
        """g_e with theta_i = sum_e g_e . u_node(e) (seed 000 eq 10), self ends last."""
        bond, d = self._end_bond, self.dim
        coef = d * w[bond] * self.length[bond] * self._end_volume / m[self._owner]
        g = (coef * self._end_sign)[:, None] * self.unit[bond]
        g_self = -torch.zeros(self.particles.n, d, dtype=g.dtype).index_add(0, self._owner, g)
        return torch.cat([g, g_self])

    def _energy_parts(self, moduli, params, delta, u, factor=1.0):
        """W_i (seed 001 eq 40) rewritten as in the module docstring, split into the
        dilatation part and the bond part (whose bonds carry the correction ``factor``)."""
        K, G = moduli["K"], moduli["G"]
        d, c = self.dim, _C_DEV[self.dim]
        w = self.bond_weight(params, delta)
        m = self.weighted_volume(w)
        theta = self._dilatation.apply(self._dilatation_vectors(w, m).reshape(-1), u.reshape(-1))
        sum_e2 = self._family_sum((factor * w * self.extension(u) ** 2)[self._end_bond] * self._end_volume)
        return 0.5 * (self.kappa(K, G) - c * G / d**2) * theta**2, 0.5 * c * G / m * sum_e2

    def _bulk_energy_parts(self, moduli, params, delta, axis: int):
        """The two parts of W for a unit uniaxial strain along ``axis`` at a particle with a
        complete lattice family (where theta = 1 exactly), per particle's moduli."""
        K, G = moduli["K"], moduli["G"]
        d, c = self.dim, _C_DEV[self.dim]
        r, n, cell = self._lattice_family
        w = self.influence(r, delta, params) * partial_volume(r, delta, self.bonds.h, self.bonds.rule)
        m = (w * r**2).sum() * cell
        sum_e2 = (w * (n[:, axis] ** 2 * r) ** 2).sum() * cell
        return 0.5 * (self.kappa(K, G) - c * G / d**2), 0.5 * c * G / m * sum_e2

    def _stiffness_terms(self, moduli, params, delta, factor=1.0):
        K, G = moduli["K"], moduli["G"]
        d, c = self.dim, _C_DEV[self.dim]
        w = self.bond_weight(params, delta)
        m = self.weighted_volume(w)
        V = self.volume
        s = V * (self.kappa(K, G) - c * G / d**2)
        k_b = factor * c * w * V[self._i] * V[self._j] * (G[self._i] / m[self._i] + G[self._j] / m[self._j])
        g = self._dilatation_vectors(w, m)
        return [(self._extension, self._extension_data, k_b), (self._dilatation, g.reshape(-1), s)]


class BondBased(_Material):
    """Prototype microelastic brittle (PMB) bond-based material, linearised.

    Params: ``{"K": bulk}`` (scalar or per particle), plus the influence function's
    parameters if any; Poisson's ratio is fixed by the model (1/4 in 3D and plane strain,
    1/3 in plane stress).
    """

    moduli_names = ("K",)

    def micromodulus(self, K: torch.Tensor, delta, params: dict) -> torch.Tensor:
        """c calibrated on the continuum family with this influence function."""
        if self.dim == 3:
            return 18 * K / (4 * math.pi * self.influence.moment(3, delta, params))
        coef = 3.0 if self.plane == "stress" else 24.0 / 5.0
        return coef * K / (math.pi * self.particles.thickness * self.influence.moment(2, delta, params))

    def _bond_stiffness(self, moduli, params, delta):
        c = self.micromodulus(moduli["K"], delta, params)
        c_b = 0.5 * (c[self._i] + c[self._j])
        w = self.bond_weight(params, delta)
        return c_b * w * self.volume[self._i] * self.volume[self._j] / self.length

    def _energy_parts(self, moduli, params, delta, u, factor=1.0):
        """(0, W_i) with W_i = 1/4 sum_j c omega beta s^2 |xi| V_j: half of each bond's
        energy to each end; every bond carries the correction ``factor``."""
        half = 0.25 * factor * self._bond_stiffness(moduli, params, delta) * self.extension(u) ** 2
        per_node = torch.zeros(self.particles.n, dtype=half.dtype).index_add(0, self._i, half).index_add(0, self._j, half)
        return torch.zeros_like(per_node), per_node / self.volume

    def _bulk_energy_parts(self, moduli, params, delta, axis: int):
        """(0, W) for a unit uniaxial strain along ``axis`` at a particle with a complete
        lattice family: W = 1/4 c sum omega beta n_a^4 |xi| V."""
        r, n, cell = self._lattice_family
        w = self.influence(r, delta, params) * partial_volume(r, delta, self.bonds.h, self.bonds.rule)
        W = 0.25 * self.micromodulus(moduli["K"], delta, params) * (w * n[:, axis] ** 4 * r).sum() * cell
        return torch.zeros_like(W), W

    def _stiffness_terms(self, moduli, params, delta, factor=1.0):
        return [(self._extension, self._extension_data, factor * self._bond_stiffness(moduli, params, delta))]
