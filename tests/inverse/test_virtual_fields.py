"""bayespd/inverse/virtual_fields.py: the virtual fields of Delorme 2018 and ours vanish where they
must (support points, patches, outside bumps), are continuous (C1 for bumps), and agree with
the paper's formulas where they should."""
import numpy as np
import pytest

from bayespd.inverse.virtual_fields import bending_fields, bump, interior_bumps, scaled, delorme_fields

L, W, S = 128.0, 32.0, 96.0  # Delorme 2018's beam
ORIGIN = (L / 2, 0.0)


def test_delorme_fields_are_the_papers_formulas_and_vanish_at_the_supports():
    """u*(1) = (|x1| - S/2) e2 and u*(2) = |x1| x1 x2 / (L W) e1 in the frame centred at
    mid-span bottom (eqs 27-28), exactly; both are 0 at the support points (+-S/2, 0) (eq 29)."""
    u1, u2 = delorme_fields(L, W, S, origin=ORIGIN)
    rng = np.random.default_rng(0)
    x = rng.uniform([0, 0], [L, W], size=(50, 2))
    x1, x2 = x[:, 0] - L / 2, x[:, 1]
    np.testing.assert_array_equal(u1(x), np.c_[np.zeros(50), np.abs(x1) - S / 2])
    np.testing.assert_allclose(u2(x), np.c_[np.abs(x1) * x1 * x2 / (L * W), np.zeros(50)], rtol=1e-15)
    supports = np.array([[L / 2 - S / 2, 0.0], [L / 2 + S / 2, 0.0]])
    assert np.all(u1(supports) == 0) and np.all(u2(supports) == 0)


def test_bending_fields_vanish_on_the_patches_and_equal_the_papers_inside():
    """With clear half width a and depth d: both fields are exactly 0 on the support patches
    |x1 -+ S/2| <= a, 0 <= x2 <= d; u*(1) is 0 outside |x1| < S/2 - a; a = d = 0 gives the
    paper's fields inside the span; both are continuous (a jump across the kinks would show
    as a difference of order 1 over a 1e-9 step)."""
    a, d = 2.0, 1.5
    u1, u2 = bending_fields(L, W, S, origin=ORIGIN, clear_half_width=a, clear_depth=d)
    rng = np.random.default_rng(1)
    for centre in (L / 2 - S / 2, L / 2 + S / 2):
        patch = np.c_[rng.uniform(centre - a, centre + a, 40), rng.uniform(0, d, 40)]
        assert np.all(u1(patch) == 0) and np.all(u2(patch) == 0)
    over = np.c_[rng.uniform(0, L / 2 - S / 2 + a, 20), rng.uniform(0, W, 20)]
    assert np.all(u1(over) == 0)
    p1, p2 = delorme_fields(L, W, S, origin=ORIGIN)
    v1, v2 = bending_fields(L, W, S, origin=ORIGIN)
    inside = np.c_[rng.uniform(L / 2 - S / 2, L / 2 + S / 2, 30), rng.uniform(0, W, 30)]
    np.testing.assert_array_equal(v1(inside), p1(inside))
    np.testing.assert_array_equal(v2(inside), p2(inside))
    kinks = np.array([[L / 2 - S / 2 + a, 5.0], [L / 2 + 10.0, d], [L / 2, 3.0]])
    for u in (u1, u2):
        for k in kinks:
            step = u(np.array([k - [1e-9, 1e-9]])) - u(np.array([k + [1e-9, 1e-9]]))
            assert np.abs(step).max() < 1e-8
    with pytest.raises(ValueError, match=">= 0"):
        bending_fields(L, W, S, clear_half_width=-1.0)


def test_bump_is_a_c1_bump_of_one_component():
    """prod_a (1 - s_a^2)^2: 1 at the centre, 0 on and outside |s_a| = 1 along with its first
    derivative: near the edge it is 4 t^2 in t = 1 - |s|, so a central difference of step
    h there is 2 h / r^2 (-> 0 with h: no kink), while inside it matches the analytic
    derivative to O(h^2); only the chosen component is non-zero."""
    u = bump((1.0, 2.0), (0.5, 1.0), component=1)
    assert np.array_equal(u(np.array([[1.0, 2.0]])), [[0.0, 1.0]])
    outside = np.array([[1.5, 2.0], [0.4, 2.0], [1.0, 3.2], [3.0, 3.0]])
    assert np.all(u(outside) == 0)
    h = 1e-4

    def ddx(x):
        return (u(np.array([[x + h, 2.0]])) - u(np.array([[x - h, 2.0]])))[0, 1] / (2 * h)

    for edge in (1.5, 0.5):  # C1 at the edge
        assert abs(ddx(edge)) == pytest.approx(2 * h / 0.5**2, rel=1e-3)
    s = 0.3 / 0.5
    assert ddx(1.3) == pytest.approx(-4 * s * (1 - s**2) / 0.5, rel=1e-7)
    assert np.all(u(np.random.default_rng(2).uniform(0, 3, (20, 2)))[:, 0] == 0)
    with pytest.raises(ValueError, match="radius must be positive"):
        bump((0.0, 0.0), (1.0, 0.0), 0)


def test_interior_bumps_tile_the_box_inside_the_clearance():
    """counts (3, 2) in 2D: 6 cells x 2 components = 12 fields; their supports lie in
    [lower + c, upper - c] and neighbouring bumps touch (the sum of the x-bumps' values is
    positive everywhere strictly inside the tiled box except on the cell edges)."""
    lower, upper, c = np.array([0.0, 0.0]), np.array([10.0, 6.0]), 1.0
    fields = interior_bumps(lower, upper, (3, 2), clearance=c)
    assert len(fields) == 12
    rng = np.random.default_rng(3)
    x = rng.uniform(lower, upper, (2000, 2))
    values = np.stack([f(x) for f in fields])  # (12, n, 2)
    outside = np.any((x < lower + c) | (x > upper - c), axis=1)
    assert np.all(values[:, outside] == 0)
    assert np.all(values[0::2, :, 1] == 0) and np.all(values[1::2, :, 0] == 0)
    assert np.all(values[0::2, ~outside, 0].sum(0) > 0)
    with pytest.raises(ValueError, match="leaves no interior"):
        interior_bumps(lower, upper, (1, 1), clearance=3.0)


def test_scaled_multiplies_by_the_weight():
    u1, _ = delorme_fields(L, W, S, origin=ORIGIN)
    weight = lambda x: (x[:, 0] > L / 2).astype(float)  # noqa: E731
    x = np.array([[10.0, 3.0], [100.0, 3.0]])
    np.testing.assert_array_equal(scaled(u1, weight)(x), u1(x) * [[0.0], [1.0]])
