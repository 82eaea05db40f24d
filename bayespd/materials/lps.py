"""Linear peridynamic solid (ordinary state-based LPS, Turner 2015 eqs 5-10, Delorme 2018 eqs 18-19,
35-45): linearised stiffness, damaged stiffness and exact-kinematics force.

With the dilatation theta_i = (d/m_i) sum_j w x e V_j, the deviatoric extension
e^d = e - theta x / d and alpha = c_d G / m (c_2 = 8, c_3 = 15), the energy density
W_i = kappa/2 theta^2 + alpha/2 sum_j w (e^d)^2 V_j rewrites, using sum_j w x e^d V_j = 0, as

    W_i = (kappa_i / 2 - c_d G_i / (2 d^2)) theta_i^2 + (c_d G_i / (2 m_i)) sum_j w e_ij^2 V_j,

so K = D^T diag(V (kappa - c_d G / d^2)) D + B^T diag(k_b) B (B maps u to bond extensions,
D = S B to dilatations, S summing each particle's bonds: ``linalg.bond_sums``) is the Hessian
of sum_i V_i W_i: symmetric even when the moduli vary from particle to particle (Turner 2015
eq 8). kappa is the in-plane bulk modulus: 9KG/(3K+4G) in plane stress, K + G/3 in plane
strain, K in 3D. This is the 2D split of Le et al. (2014) and equals Delorme 2018's eqs
18-19 (which use the 3D split x theta/3 in 2D: expanding eq 45 with eq 41 gives the same
coefficient 2(K + G/3)/q of theta x in plane strain). Turner 2015 prints k + mu/9 for that coefficient; the calibration above gives k + mu/3.
Every bond carries the weight omega(|xi|, delta) * beta(delta); LPS needs no recalibration
for omega: m absorbs it.

Damage and exact kinematics (``bayespd.nonlinear``): the same energy with the exact extension
and the intact weights mu w: m_i = sum_j mu w |xi|^2 V_j, theta_i = (d / m_i) sum_j mu w |xi| e V_j,

    V_i W_i = V_i [(kappa_i/2 - c_d G_i/(2 d^2)) theta_i^2 + (c_d G_i/(2 m_i)) sum_j mu w e^2 V_j].

m_i is floored at ``M_FLOOR`` times its undamaged value: a fully broken particle (theta = 0,
no bond energy) then divides 0 by a positive number; above the floor nothing changes, below it
the particle's energy fades continuously to zero with its last bonds. The damaged linearised
stiffness (``terms(params, intact)``) is the Hessian of this energy at u = 0.
"""
from __future__ import annotations

import torch

from bayespd.linalg.bond_sums import BondSums
from bayespd.materials.base import Force, Material

M_FLOOR = 1e-9
C_DEV = {2: 8.0, 3: 15.0}  # c_d of alpha = c_d G / m


class LPS(Material):
    """Linear peridynamic solid (state-based), 2D plane stress / plane strain or 3D.

    Params: ``{"K": bulk, "G": shear, "delta": horizon}`` (3D moduli; scalars or per-particle
    tensors), plus the influence function's parameters if it has any.
    """

    moduli_names = ("K", "G")

    def __init__(self, particles, bonds, plane: str = "stress", influence=None,
                 surface_correction: bool = False):
        super().__init__(particles, bonds, plane, influence, surface_correction)
        n, d = particles.n, self.dim
        self.c_d = C_DEV[d]
        # D: dilatations theta = S e, each particle's sum of its bonds' extensions (eq 10), factored
        self._dilatation = BondSums(self.extension_gram, self.extension_data, n)
        self._kept_family = (None, None)  # (horizon key, (w, m, s)) of ``family``

    def grams(self) -> list:
        return [self.extension_gram, self._dilatation]

    def kappa(self, K: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
        """In-plane bulk modulus of the dimension-reduced continuum."""
        if self.dim == 3:
            return K
        return 9 * K * G / (3 * K + 4 * G) if self.plane == "stress" else K + G / 3

    def _family_sum(self, at_i: torch.Tensor, at_j: torch.Tensor) -> torch.Tensor:
        """Per-particle sum of per-bond values at_i (to end i) and at_j (to end j)."""
        z = torch.zeros(self.particles.n, dtype=at_i.dtype)
        return z.index_add_(0, self.i, at_i).index_add_(0, self.j, at_j)

    def _family_volume(self, w: torch.Tensor) -> torch.Tensor:
        wL2 = w * self.length**2
        V = self.volume
        return self._family_sum(wL2 * V.index_select(0, self.j), wL2 * V.index_select(0, self.i))

    def weighted_volume(self, w: torch.Tensor) -> torch.Tensor:
        """m_i = sum_j omega beta |xi|^2 V_j (Turner 2015 eq 9) for bond weights w."""
        m = self._family_volume(w)
        if bool(torch.any(m <= 0)):
            raise ValueError("a particle has a non-positive weighted volume m: the influence "
                             "function must be non-negative on average over each family")
        return m

    def _dilatation_weights(self, w, m):
        """(2, nb): s with theta = S e (Turner 2015 eq 10), (d w |xi| V_j / m_i, d w |xi| V_i / m_j)
        to the bond's first and second particle (``BondSums``)."""
        V, i, j = self.volume, self.i, self.j
        wL = self.dim * w * self.length  # gathers by index_select: its backward is an index_add too
        return torch.stack([wL * V.index_select(0, j) / m.index_select(0, i),
                            wL * V.index_select(0, i) / m.index_select(0, j)])

    def family(self, params):
        """(w, m, s): bond weights, weighted volumes (eq 9) and dilatation weights (eq 10) at
        params' horizon and influence parameters. The latest is kept while those are numbers
        that need no gradient (a calibration over moduli at a fixed horizon; the surface
        correction's probes): ``terms`` and ``energy_parts`` then skip them (~0.25 CPU-s
        at 160k particles in 2D)."""
        key, kept = self._kept(params)
        if kept is not None:
            return kept
        w, m = self._weights(params)
        family = (w, m, self._dilatation_weights(w, m))
        self._kept_family = (key, family) if key is not None else (None, None)
        return family

    def _kept(self, params):
        """(key, the kept family or None): its key is params' horizon and influence parameters."""
        key = _constant_key(params, ("delta", *self.influence.param_names))
        return key, (self._kept_family[1] if key is not None and self._kept_family[0] == key else None)

    def _weights(self, params):
        """(w, m) of ``family`` without the dilatation vectors (the kept ones when kept)."""
        _, kept = self._kept(params)
        if kept is not None:
            return kept[:2]
        w = self.bond_weight(params)
        return w, self.weighted_volume(w)

    def _bond_stiffness(self, G, w, m, factor):
        """k_b = factor c_d w V_i V_j (G_i / m_i + G_j / m_j) (module docstring)."""
        V, i, j = self.volume, self.i, self.j
        a = G / m  # per particle, then gathered: (G / m)[i] = G[i] / m[i] to the bit
        return factor * self.c_d * w * V.index_select(0, i) * V.index_select(0, j) * (a.index_select(0, i) + a.index_select(0, j))

    def form(self, params, v, u):
        """v^T K(params) u (``Material.form``) with the dilatations taken from the bond
        extensions, theta_i = (d / m_i) sum_j w |xi| e_ij V_j (Turner 2015 eq 10): O(bonds),
        without the dilatation weights s (the adjoint's
        form gradient builds no dilatation weights)."""
        moduli = self.moduli(params)
        w, m = self._weights(params)
        V, i, j = self.volume, self.i, self.j
        k_b = self._bond_stiffness(moduli["G"], w, m, self.bond_correction(moduli, params))
        s = V * self.term_coefficients(moduli)[1]  # k_b first: the gradient sums into G in the same order, bit for bit
        wL = self.dim * w * self.length
        at_i, at_j = wL * V.index_select(0, j), wL * V.index_select(0, i)
        e_v, e_u = self.extension(v), self.extension(u)
        theta_v = self._family_sum(at_i * e_v, at_j * e_v) / m
        theta_u = self._family_sum(at_i * e_u, at_j * e_u) / m
        return (k_b * e_v * e_u).sum() + (s * theta_v * theta_u).sum()

    def term_coefficients(self, moduli):
        """(G, kappa - c_d G / d^2): the factors of the bond and the dilatation term."""
        K, G = moduli["K"], moduli["G"]
        return [G, self.kappa(K, G) - self.c_d * G / self.dim**2]

    def energy_parts(self, moduli, params, u, factor=1.0):
        """W_i (Delorme 2018 eq 40) rewritten as in the module docstring, split into the
        dilatation part and the bond part (whose bonds carry the correction ``factor``)."""
        K, G = moduli["K"], moduli["G"]
        d, c = self.dim, self.c_d
        w, m, s = self.family(params)
        theta = self._dilatation.apply(s, u.reshape(-1))
        we2 = factor * w * self.extension(u) ** 2
        sum_e2 = self._family_sum(we2 * self.volume[self.j], we2 * self.volume[self.i])
        return 0.5 * (self.kappa(K, G) - c * G / d**2) * theta**2, 0.5 * c * G / m * sum_e2

    def bulk_energy_parts(self, moduli, params, axis: int):
        """The two parts of W for a unit uniaxial strain along ``axis`` at a particle with a
        complete lattice family (where theta = 1 exactly), per particle's moduli."""
        K, G = moduli["K"], moduli["G"]
        d, c = self.dim, self.c_d
        r, n, cell = self.lattice_family
        w = self.lattice_weight(r, params)
        m = (w * r**2).sum() * cell
        sum_e2 = (w * (n[:, axis] ** 2 * r) ** 2).sum() * cell
        return 0.5 * (self.kappa(K, G) - c * G / d**2), 0.5 * c * G / m * sum_e2

    def stiffness_terms(self, moduli, params, factor=1.0, intact=None):
        """K = B^T diag(k_b) B + D^T diag(s) D (module docstring); with ``intact`` the bond
        weights are mu w and m is floored at M_FLOOR times its undamaged value."""
        w, m, s = self.family(params)
        if intact is not None:
            w = w * intact
            m = torch.maximum(self._family_volume(w), M_FLOOR * m)
            s = self._dilatation_weights(w, m)
        k_b = self._bond_stiffness(moduli["G"], w, m, factor)
        return [(self.extension_gram, self.extension_data, k_b),
                (self._dilatation, s, self.volume * self.term_coefficients(moduli)[1])]

    def nonlinear(self, kinematics, params, dtype=torch.float64):
        return LPSForce(kinematics, params, dtype)


def _constant_key(params: dict, names) -> tuple | None:
    """The values of ``params[names]`` as a key when each is a number or a small tensor that
    needs no gradient (grad disabled, or not requiring it); else None."""
    key = []
    for name in names:
        v = params[name]
        if isinstance(v, torch.Tensor):
            if (v.requires_grad and torch.is_grad_enabled()) or v.numel() > 16:
                return None
            key.append((v.dtype, tuple(v.detach().reshape(-1).tolist())))
        elif isinstance(v, (int, float)):
            key.append((torch.float64, (float(v),)))
        else:
            return None
    return tuple(key)


class LPSForce(Force):
    """LPS: dV/de_b = mu w V_i V_j [|xi| (a_i + a_j) + F_b e (b_i + b_j)] with
    a = 2 d A theta / m, b = c_d G / m, A = kappa/2 - c_d G/(2 d^2), F_b the surface factor."""

    def __init__(self, kin, params, dtype=torch.float64):
        super().__init__(kin, params, dtype)
        mat, d, L = kin.material, kin.dim, kin.length
        K, G = self.moduli["K"], self.moduli["G"]
        w = mat.bond_weight(params)
        Vi, Vj = mat.volume[kin.i], mat.volume[kin.j]
        coef = {"A": 0.5 * (mat.kappa(K, G) - mat.c_d * G / d**2), "cG": mat.c_d * G,
                "m0": mat.weighted_volume(w), "volume": mat.volume,
                "wVVL": w * Vi * Vj * L, "wVVF": w * Vi * Vj * self.factor,
                "wLVi": w * L * Vi, "wLVj": w * L * Vj}
        for name, value in coef.items():
            setattr(self, name, value.to(dtype))

    def _sum(self, at_i, at_j):
        """Per-particle sum of per-bond values at_i (to end i) and at_j (to end j)."""
        z = torch.zeros(self.kin.n, dtype=at_i.dtype)
        return z.index_add_(0, self.kin.i, at_i).index_add_(0, self.kin.j, at_j)

    def _state(self, u, intact, components=None):
        """(y, |y|, mu e, e, m, theta, mu); mu e stands for e when there is no damage."""
        kin = self.kin
        intact = self._intact(u, intact)
        y, r, e = components or kin.components(u)
        if intact is None:
            me, m = e, self.m0
        else:
            me = e * intact
            wL2 = intact * kin.geometry(self.dtype)[1]
            m = torch.maximum(self._sum(wL2 * self.wLVj, wL2 * self.wLVi), M_FLOOR * self.m0)
        theta = kin.dim / m * self._sum(self.wLVj * me, self.wLVi * me)
        return y, r, me, e, m, theta, intact

    def force(self, u, intact=None, components=None):
        kin = self.kin
        y, r, me, e, m, theta, intact = self._state(u, intact, components)
        ab = torch.stack([2 * kin.dim * self.A * theta / m, self.cG / m], dim=1)
        ab = ab.index_select(0, kin.i) + ab.index_select(0, kin.j)
        bond = self.wVVL * ab[:, 0] if intact is None else self.wVVL * intact * ab[:, 0]
        t = torch.addcmul(bond, self.wVVF * me, ab[:, 1])
        return self._scatter(y, t / r, u)

    def strain_energy(self, u, intact=None):
        y, r, me, e, m, theta, _ = self._state(u, intact)
        b = self.cG / m
        bond = 0.5 * self.wVVF * me * e * (b[self.kin.i] + b[self.kin.j])
        return (self.volume * self.A * theta**2).sum() + bond.sum()
