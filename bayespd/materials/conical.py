"""Bond-based material with a conical micromodulus c(|xi|) = c0 (1 - |xi|/delta)_+: stiff
short bonds, soft long ones, so the bond stiffness falls continuously to zero at the horizon
(Ha & Bobaru 2010's "conical" micromodulus; Dodwell 2019 eq 1 with c depending on |xi|).

Calibration on the continuum family (as ``pmb``): an isotropic expansion u = eps x stretches
every bond by s = eps, and W = 1/4 int c(r) omega(r) s^2 r dV must equal the classical density.
With C_k = int_0^delta omega r^k (1 - r/delta) dr = M_k - M_(k+1)/delta:

    3D:            4 pi c0 C_3 eps^2 / 4 = 9 K eps^2 / 2        =>  c0 = 18 K / (4 pi C_3)
    plane stress:  2 pi t c0 C_2 eps^2 / 4 = 3 K eps^2 / 2       =>  c0 = 3 K / (pi t C_2)
    plane strain:  2 pi t c0 C_2 eps^2 / 4 = 12 K eps^2 / 5     =>  c0 = 24 K / (5 pi t C_2)

(plane stress: nu = 1/3, in-plane bulk 3K/4, W = 2 (3K/4) eps^2; plane strain: nu = 1/4,
in-plane bulk 6K/5). For omega = 1, C_2 = delta^3/12 and C_3 = delta^4/20:
c0 = 90 K / (pi delta^4) in 3D, 36 K / (pi t delta^3) in plane stress and
288 K / (5 pi t delta^3) in plane strain.

The profile is a factor of each bond's weight (omega beta (1 - |xi|/delta)_+), so the linear,
damaged and nonlinear forms, the surface correction and the compiled loops of ``BondBased``
all carry it.
"""
from __future__ import annotations

import torch

from bayespd.materials.pmb import BondBased


class ConicalBondBased(BondBased):
    """Bond-based material with micromodulus c0 (1 - |xi|/delta)_+ (module docstring).

    Params: ``{"K": bulk, "delta": horizon}`` plus the influence function's parameters;
    Poisson's ratio is fixed as for ``BondBased``.
    """

    @staticmethod
    def profile(r: torch.Tensor, delta) -> torch.Tensor:
        """(1 - r/delta)_+, the shape of the micromodulus."""
        return torch.clamp(1 - r / delta, min=0.0)

    def moment(self, k: int, params: dict) -> torch.Tensor:
        """C_k = M_k - M_(k+1) / delta = int_0^delta omega r^k (1 - r/delta) dr."""
        delta = params["delta"]
        return self.influence.moment(k, delta, params) - self.influence.moment(k + 1, delta, params) / delta

    def bond_weight(self, params: dict) -> torch.Tensor:
        return super().bond_weight(params) * self.profile(self.length, params["delta"])

    def lattice_weight(self, r: torch.Tensor, params: dict) -> torch.Tensor:
        return super().lattice_weight(r, params) * self.profile(r, params["delta"])
