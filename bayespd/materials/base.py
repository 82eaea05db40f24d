"""The material contract: what every peridynamic law gives the rest of bayespd.

A material is built on particles and bonds (found once at delta_max) and evaluated at a
``params`` dict holding its moduli (``moduli_names``), its influence function's parameters
and the horizon ``"delta"`` -- all ordinary parameters, scalars or per-particle tensors,
differentiable (principle 3-4 of DESIGN.md). Its linearised stiffness is a list of Gram terms
(operator A_t, data, weights k_t): K = sum_t A_t^T diag(k_t) A_t on the fixed ``pattern``.

A law subclasses ``Material`` and writes five methods:

* ``stiffness_terms(moduli, params, factor, intact)``: the Gram terms of K at the per-bond
  intact fractions mu (``intact``; None: all intact), bond terms times the surface ``factor``;
* ``term_coefficients(moduli)``: the scalar factors Theta_t of its terms for homogeneous
  moduli (K = sum_t Theta_t A_t(delta), the affine structure a reduced model keeps);
* ``energy_parts(moduli, params, u, factor)``: (W_fixed, W_bond) per particle for a
  displacement u, the split the surface correction needs (``bayespd.surface``);
* ``bulk_energy_parts(moduli, params, axis)``: the same two parts at a complete lattice
  family (``lattice_family``) under a unit uniaxial strain along ``axis``;
* ``nonlinear(kinematics, params, dtype)``: its exact-kinematics force (a ``Force``).

``pairwise`` says whether the nonlinear bond force is t_b = k_b mu_b e_b with the per-bond
stiffness ``force.k`` (bond-based laws): then the exact bond Hessian is known (quasi-static
Newton) and the compiled ``bond_loops`` apply. Everything else here is shared.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from functools import cached_property

import numpy as np
import torch

from bayespd.bonds import Bonds, partial_volume
from bayespd.discretize import Particles
from bayespd.influence import Constant, Influence
from bayespd.linalg.assembly import Gram, numeric_values, union_pattern
from bayespd.linalg.page_advice import without_huge_pages
from bayespd.materials.checks import check_modulus
from bayespd.nonlinear import product
from bayespd.surface import bond_factors


class Material(ABC):
    """A peridynamic law on fixed particles and bonds (see the module docstring).

    ``influence`` weights the bonds (default constant); ``surface_correction=True`` scales
    each bond's stiffness by energy-based directional factors (see ``bayespd.surface``).
    Public geometry: ``particles``, ``bonds``, ``dim``, ``volume`` (N,), bond ``length``,
    ``unit`` directions and ends ``i``, ``j`` (tensors).
    """

    moduli_names: tuple[str, ...] = ()
    pairwise: bool = False

    @without_huge_pages()
    def __init__(self, particles: Particles, bonds: Bonds, plane: str = "stress",
                 influence: Influence | None = None, surface_correction: bool = False):
        if plane not in ("stress", "strain"):
            raise ValueError("plane must be 'stress' or 'strain'")
        self.particles, self.bonds, self.plane = particles, bonds, plane
        self.influence = influence or Constant()
        self.surface_correction = surface_correction
        self.param_names = (*self.moduli_names, *self.influence.param_names, "delta")
        self.dim = d = particles.dim
        self.volume = torch.as_tensor(particles.volume)
        self.length = torch.as_tensor(bonds.length)
        self.unit = torch.as_tensor(bonds.xi / bonds.length[:, None])
        self.i, self.j = torch.as_tensor(bonds.i), torch.as_tensor(bonds.j)
        # B: bond extensions e_b = n . (u_j - u_i); entries (b, d*i+a) = -n_a, (b, d*j+a) = n_a
        self.extension_gram = Gram.of_blocks(np.stack([bonds.i, bonds.j], axis=1), d * particles.n, d)
        self.extension_data = torch.cat([-self.unit, self.unit], dim=1).reshape(-1)

    def copies(self, k: int) -> "Material":
        """``k`` copies of this body side by side as one body, no bond between them (particle
        c n + p is copy c's p moved by c ``copy_shift`` along x): one run of it is k runs of the
        body, e.g. at k damage laws."""
        p, shift = self.particles, self.copy_shift
        x = np.concatenate([p.x + np.eye(self.dim)[0] * shift * c for c in range(k)])
        return type(self)(Particles(x, np.tile(p.volume, k), p.h, p.thickness), self.bonds.tiled(k, p.n), self.plane,
                          self.influence, self.surface_correction)

    @property
    def copy_shift(self) -> float:
        """The x distance between ``copies``: the body's width, a step h and two horizons, in whole
        steps h (copies of a lattice lie on one lattice)."""
        p = self.particles
        return p.h * float(np.ceil((np.ptp(p.x[:, 0]) + p.h + 2 * self.bonds.delta_max) / p.h))

    def in_body(self, points) -> np.ndarray:
        """Points (M, dim) about ``copies`` moved back by their copy's shift: the same places in
        this body's coordinates (a copy owns the space up to halfway to its neighbours)."""
        x, shift = self.particles.x[:, 0], self.copy_shift
        start = x.min() - (shift - np.ptp(x)) / 2
        points = np.array(points, float)
        points[:, 0] -= shift * np.floor((points[:, 0] - start) / shift)
        return points

    def grams(self) -> list[Gram]:
        """The Gram operators of the stiffness terms; the bond extensions B first."""
        return [self.extension_gram]

    @cached_property
    def pattern(self):
        return union_pattern(self.grams())

    def bond_weight(self, params: dict) -> torch.Tensor:
        """omega(|xi|, delta) * beta(delta) per bond; refuses particles left without a family."""
        delta = params["delta"]
        w = self.influence(self.length, delta, params) * self.bonds.weight(delta)
        if self._every_particle_bonded and bool(torch.all(w != 0)):
            return w  # every family holds a bond of nonzero weight (volumes are positive)
        V = self.volume
        family = torch.zeros(self.particles.n, dtype=w.dtype).index_add(
            0, self.i, w.abs() * V.index_select(0, self.j)).index_add(0, self.j, w.abs() * V.index_select(0, self.i))
        if bool(torch.any(family == 0)):
            k = int(torch.nonzero(family == 0)[0])
            raise ValueError(f"particle {k} at {self.particles.x[k].tolist()} has an empty family "
                             "at this horizon: increase delta or remove isolated particles")
        return w

    @cached_property
    def _every_particle_bonded(self) -> bool:
        return bool(np.all(np.bincount(np.concatenate([self.bonds.i, self.bonds.j]), minlength=self.particles.n)))

    def lattice_weight(self, r: torch.Tensor, params: dict) -> torch.Tensor:
        """omega * beta of the bonds of length r of ``lattice_family``."""
        delta = params["delta"]
        return self.influence(r, delta, params) * partial_volume(r, delta, self.bonds.h, self.bonds.rule)

    @cached_property
    def lattice_family(self):
        """Offsets of a complete family on the regular lattice of spacing h, up to delta_max
        + h/2: (lengths, units, cell volume), the bulk reference of the surface correction."""
        h, d = self.bonds.h, self.dim
        k = np.arange(-math.ceil(self.bonds.delta_max / h) - 1, math.ceil(self.bonds.delta_max / h) + 2)
        xi = h * np.stack(np.meshgrid(*[k] * d, indexing="ij"), axis=-1).reshape(-1, d)
        r = np.linalg.norm(xi, axis=1)
        keep = (r > 0) & (r < self.bonds.delta_max + h / 2)
        cell = h**d * (self.particles.thickness if d == 2 else 1.0)
        return torch.as_tensor(r[keep]), torch.as_tensor(xi[keep] / r[keep, None]), cell

    def moduli(self, params: dict) -> dict:
        """The checked moduli, each expanded to one value per particle; refuses params that
        lack a name of ``param_names`` (the horizon included: params["delta"])."""
        missing = set(self.param_names) - set(params)
        if missing:
            hint = " (the horizon is a parameter: pass params['delta'])" if "delta" in missing else ""
            raise ValueError(f"{type(self).__name__} needs params {sorted(missing)} "
                             f"(has {list(self.param_names)}){hint}")
        n = self.particles.n
        return {k: check_modulus(k, params[k], n).expand(n) for k in self.moduli_names}

    def bond_correction(self, moduli: dict, params: dict):
        """Surface-correction factor per bond, or 1 when the correction is off."""
        return bond_factors(self, moduli, params) if self.surface_correction else 1.0

    def check_intact(self, intact) -> torch.Tensor:
        """Per-bond intact fractions mu as float64, one per bond."""
        intact = torch.as_tensor(intact, dtype=torch.float64)
        if intact.shape != self.length.shape:
            raise ValueError(f"intact needs one value per bond ({self.length.shape[0]})")
        return intact

    def terms(self, params: dict, intact=None):
        """Gram terms of K(params) at the intact fractions ``intact`` (None: undamaged): the
        Hessian at u = 0 of the nonlinear energy with bond weights w -> mu w."""
        if intact is not None:
            intact = self.check_intact(intact)
        moduli = self.moduli(params)
        return self.stiffness_terms(moduli, params, self.bond_correction(moduli, params), intact)

    def energy_density(self, params: dict, u: torch.Tensor) -> torch.Tensor:
        """W_i per particle for u of shape (N, dim) (surface-corrected when switched on)."""
        moduli = self.moduli(params)
        return sum(self.energy_parts(moduli, params, u, self.bond_correction(moduli, params)))

    def stiffness(self, params: dict, rows=None) -> torch.Tensor:
        """Values of K(params) on ``self.pattern`` (on its entries in K's ``rows`` only, in the
        pattern's order, when given), differentiable (twice)."""
        return sum(g.values(d, w, self.pattern, rows) for g, d, w in self.terms(params))

    def numeric_stiffness(self, params: dict, intact=None) -> torch.Tensor:
        """The values of K (at ``intact``, see ``terms``) assembled by scipy (no autograd
        graph; for factorisation)."""
        with torch.no_grad():
            return numeric_values(self.pattern, self.terms(params, intact))

    def form(self, params: dict, v: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """v^T K(params) u matrix-free: sum_t sum_r w_r (A_t v)_r (A_t u)_r."""
        v, u = v.reshape(-1), u.reshape(-1)
        return sum((w * g.apply(d, v) * g.apply(d, u)).sum() for g, d, w in self.terms(params))

    def energy(self, params: dict, u: torch.Tensor) -> torch.Tensor:
        """Total strain energy sum_i V_i W_i = u^T K u / 2 of the linearised model."""
        return 0.5 * self.form(params, u, u)

    def extension(self, u: torch.Tensor) -> torch.Tensor:
        """Linearised bond extension e = n . (u_j - u_i) for u of shape (N, dim)."""
        return self.extension_gram.apply(self.extension_data, u.reshape(-1))

    @abstractmethod
    def stiffness_terms(self, moduli: dict, params: dict, factor=1.0, intact=None) -> list:
        """Gram terms [(A_t, data, k_t)] at intact fractions ``intact`` (None: all intact),
        the bond terms times the surface ``factor``."""

    @abstractmethod
    def term_coefficients(self, moduli: dict) -> list:
        """Theta_t per stiffness term for homogeneous (scalar) moduli: term t's weights are
        Theta_t times a function of delta (and the influence parameters) alone, so that
        K = sum_t Theta_t(moduli) A_t(delta), the affine structure ``bayespd.reduced`` keeps."""

    @abstractmethod
    def energy_parts(self, moduli: dict, params: dict, u: torch.Tensor, factor=1.0):
        """(W_fixed, W_bond) per particle at u (N, dim); W_bond's bonds carry ``factor``."""

    @abstractmethod
    def bulk_energy_parts(self, moduli: dict, params: dict, axis: int):
        """(W_fixed, W_bond) at a complete lattice family under unit strain along ``axis``."""

    @abstractmethod
    def nonlinear(self, kinematics, params: dict, dtype=torch.float64) -> "Force":
        """The exact-kinematics force at ``params`` for ``kinematics`` (a ``NonlinearBonds``)."""


class Force(ABC):
    """A law's exact-kinematics force at one params (Dodwell 2019 eqs 2-3): ``force(u, intact,
    components)``, ``strain_energy(u, intact)`` and ``energy(u, intact, load, eps)``;
    ``kin`` is the ``nonlinear.NonlinearBonds`` of the material."""

    def __init__(self, kin, params: dict, dtype=torch.float64):
        self.kin, self.dtype = kin, dtype
        self.moduli = kin.material.moduli(params)
        self.factor = kin.material.bond_correction(self.moduli, params)

    def _intact(self, u, intact):
        """The intact fractions in this dtype; refuses a u of another dtype (the coefficients
        were converted once, in ``NonlinearBonds.at``)."""
        if u.dtype != self.dtype:
            raise ValueError(f"u is {u.dtype} but these coefficients are {self.dtype}: "
                             f"use NonlinearBonds.at(params, dtype={u.dtype})")
        return None if intact is None else torch.as_tensor(intact).to(self.dtype)

    def _scatter(self, y, t_over_r, like):
        """Bond force t y/|y| pulls i towards j and j towards i: f = -D^T (t y / |y|) (negated
        after the sum, on the particles' values: the same bits, one pass over the bonds less)."""
        fb = (y * t_over_r).reshape(-1)
        D, DT = self.kin.incidence(fb)
        return -product(DT, D, fb).view(like.shape)

    def energy(self, u, intact=None, load=None, eps: float = 0.0):
        """Strain energy - p . u + (eps/2) u . u (Dodwell 2019 eq 3)."""
        V = self.strain_energy(u, intact)
        if load is not None:
            V = V - (torch.as_tensor(load) * u).sum()
        return V + 0.5 * eps * (u * u).sum()

    @abstractmethod
    def force(self, u, intact=None, components=None) -> torch.Tensor:
        """-dV_strain/du (N, dim) at intact fractions ``intact`` (``components``: those of
        ``NonlinearBonds.components(u)``, when known)."""

    @abstractmethod
    def strain_energy(self, u, intact=None) -> torch.Tensor:
        """The strain energy at u and ``intact``."""
