"""Checks shared by every material law: moduli in range, and moduli from (E, nu)."""
from __future__ import annotations

import torch

from bayespd.validate import positive


def moduli_from_young(E, nu):
    """Bulk and shear moduli (K, G) from Young's modulus and Poisson's ratio:
    K = E / (3 (1 - 2 nu)), G = E / (2 (1 + nu)).

    K is the **3D** bulk modulus in every case, plane stress and plane strain included: it is
    what ``bp.LPS(..., plane=...)`` takes (the law forms its in-plane modulus ``kappa`` from
    it) and what the VFM and the fits return. Inverse: :func:`young_from_moduli`."""
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


PLANES = (None, "stress", "strain")


def young_from_moduli(K, G, plane=None):
    """Young's modulus and Poisson's ratio (E, nu) from bulk and shear moduli, the inverse of
    :func:`moduli_from_young`: E = 9 K G / (3 K + G), nu = (3 K - 2 G) / (2 (3 K + G)).

    ``K`` is the **3D** bulk modulus, as ``bp.LPS`` takes it and the fits return it, for every
    ``plane`` (None, "stress" or "strain"): E and nu are material constants, so the answer is
    the same in plane stress and plane strain, and ``plane`` is only checked. (The in-plane
    modulus ``LPS.kappa`` is 9 K G / (3 K + 4 G) = E / (2 (1 - nu)) in plane stress and
    K + G / 3 in plane strain: do not pass it as K.)"""
    if plane not in PLANES:
        raise ValueError(f"plane must be one of {PLANES}, got {plane!r}: K is the 3D bulk "
                         "modulus in every case, so (E, nu) do not depend on it")
    K = torch.as_tensor(positive("K", K, "pass the 3D bulk modulus, finite and > 0"))
    G = torch.as_tensor(positive("G", G, "pass the shear modulus, finite and > 0"))
    E, nu = 9 * K * G / (3 * K + G), (3 * K - 2 * G) / (2 * (3 * K + G))
    return E, nu


MODULUS_RANGE = (1e-100, 1e100)  # LPS solves lose every digit below ~1e-160; K ~ 1e200 overflows


class ParameterRangeError(ValueError):
    """A modulus outside (0, inf): bad input, or a sampler's or optimiser's trial point that
    over- or underflowed (which the inference code treats as a rejected proposal)."""


class NonFiniteParameterError(ParameterRangeError):
    """A modulus is NaN or inf."""


def check_modulus(name: str, value, n: int) -> torch.Tensor:
    """A modulus as a tensor broadcastable to (n,); refuse NaN, inf and non-positive values."""
    try:
        v = torch.as_tensor(value)
    except (TypeError, ValueError, RuntimeError) as error:
        raise TypeError(f"{name} must be a number or a tensor of numbers, got {value!r}") from error
    if v.dim() > 1 or (v.dim() == 1 and v.shape[0] != n):
        raise ValueError(f"{name} must be a scalar or have one value per particle ({n})")
    if not bool(torch.all(torch.isfinite(v))):
        raise NonFiniteParameterError(f"{name} contains NaN or inf: pass finite moduli")
    if not bool(torch.all(v > 0)):
        raise ParameterRangeError(f"{name} must be positive (got min {float(v.min()):g}): moduli "
                         "are positive; sample them on a log scale")
    if not bool(torch.all((v >= MODULUS_RANGE[0]) & (v <= MODULUS_RANGE[1]))):
        extreme = float(v.max()) if bool(torch.any(v > MODULUS_RANGE[1])) else float(v.min())
        raise ParameterRangeError(f"{name}={extreme:g} lies outside [{MODULUS_RANGE[0]:g}, {MODULUS_RANGE[1]:g}]: "
                                  "the stiffness products under- or overflow float64 there; rescale the "
                                  "units (moduli in MPa or GPa are of order 1 to 1e6)")
    return v
