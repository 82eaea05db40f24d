"""Virtual displacement fields for the PD Virtual Fields Method (Delorme 2018 §4.2).

A virtual field is any plain callable ``u_star(x) -> (N, dim)`` of reference positions
``x`` (N, dim) (numpy); :mod:`bayespd.inverse.vfm` evaluates it at the particles and checks
that it is kinematically admissible for the scene it is used with.

Coordinates: Delorme 2018 puts the origin at mid-span on the bottom face (x1 along the beam, x2
up). The builders below take ``origin`` = where that point lies in the caller's frame (for
``bayespd.reference.three_point_bending``, whose origin is the bottom-left corner, it is
``(L/2, 0)``).
"""
from __future__ import annotations

import numpy as np


def _local(x, origin):
    x = np.asarray(x, dtype=float)
    return x[:, 0] - origin[0], x[:, 1] - origin[1]


def delorme_fields(length: float, width: float, span: float, origin=(0.0, 0.0)):
    """The two fields of Delorme 2018 verbatim (eqs 27-28), for point supports at (+-S/2, 0):

        u*(1) = (|x1| - S/2) e2,      u*(2) = (|x1| x1 x2 / (L W)) e1.

    They vanish at the two support *points* only (eq 29): with supports spread over patches
    (as in ``bayespd.reference.three_point_bending``) they are not admissible, and
    :func:`bending_fields` gives the variants that are.
    """
    half = span / 2

    def u1(x):
        x1, x2 = _local(x, origin)
        return np.stack([np.zeros_like(x1), np.abs(x1) - half], axis=1)

    def u2(x):
        x1, x2 = _local(x, origin)
        return np.stack([np.abs(x1) * x1 * x2 / (length * width), np.zeros_like(x1)], axis=1)

    return [u1, u2]


def bending_fields(length: float, width: float, span: float, origin=(0.0, 0.0),
                   clear_half_width: float = 0.0, clear_depth: float = 0.0):
    """Delorme 2018's eqs 27-28 made to vanish on support patches |x1 -+ S/2| <= a, 0 <= x2 <= d
    (a = ``clear_half_width``, d = ``clear_depth``; our adaptation, not in the paper):

        u*(1) = min(|x1| - (S/2 - a), 0) e2,
        u*(2) = (|x1| x1 max(x2 - d, 0) / (L W)) e1.

    u*(1) is the paper's field inside the span, shifted so that it reaches zero at the inner
    edge of each patch, and zero over the patches and the overhangs (which are nearly stress
    free). u*(2) is the paper's field lifted off the bottom band x2 <= d that holds the
    patches. Both are continuous and piecewise polynomial; a = d = 0 gives fields equal to
    eqs 27-28 inside the span.
    """
    if clear_half_width < 0 or clear_depth < 0:
        raise ValueError("clear_half_width and clear_depth must be >= 0")
    edge = span / 2 - clear_half_width

    def u1(x):
        x1, x2 = _local(x, origin)
        return np.stack([np.zeros_like(x1), np.minimum(np.abs(x1) - edge, 0.0)], axis=1)

    def u2(x):
        x1, x2 = _local(x, origin)
        lifted = np.maximum(x2 - clear_depth, 0.0)
        return np.stack([np.abs(x1) * x1 * lifted / (length * width), np.zeros_like(x1)], axis=1)

    return [u1, u2]


def scaled(field, weight):
    """The field multiplied by a scalar weight function ``weight(x) -> (N,)``: e.g. a cut-off
    that is zero where data are missing (the field then needs no data there)."""

    def u(x):
        return np.asarray(field(x), dtype=float) * np.asarray(weight(x), dtype=float)[:, None]

    return u


def bump(centre, radius, component: int):
    """A smooth (C1) bump along one axis: prod_a (1 - s_a^2)^2 on |s_a| < 1, s = (x - centre) /
    radius, zero elsewhere (our addition to Delorme 2018's fields).

    Placed at least two horizons inside the free surfaces, a bump needs no data near them and
    sees no PD surface effect; with no load under it, W*_ext = 0 and its equation constrains
    only the ratio of the moduli (it measures the local equilibrium of the trial stress).
    """
    centre, radius = np.asarray(centre, dtype=float), np.asarray(radius, dtype=float)
    if np.any(radius <= 0):
        raise ValueError("bump radius must be positive")

    def u(x):
        s = (np.asarray(x, dtype=float) - centre) / radius
        b = np.prod(np.where(np.abs(s) < 1, (1 - s**2) ** 2, 0.0), axis=1)
        out = np.zeros_like(s)
        out[:, component] = b
        return out

    return u


def interior_bumps(lower, upper, counts, clearance: float):
    """Bumps along each axis on a regular grid of ``counts`` cells inside the box
    [lower + clearance, upper - clearance] (one bump per cell, touching its neighbours)."""
    lo = np.asarray(lower, dtype=float) + clearance
    hi = np.asarray(upper, dtype=float) - clearance
    counts = np.asarray(counts)
    if np.any(hi <= lo):
        raise ValueError(f"clearance {clearance:g} leaves no interior in the box: reduce it")
    radius = (hi - lo) / counts / 2
    fields = []
    for idx in np.ndindex(*counts):
        centre = lo + radius * (2 * np.asarray(idx) + 1)
        fields += [bump(centre, radius, c) for c in range(len(lo))]
    return fields
