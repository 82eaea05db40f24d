"""The damage-error decomposition's field operations (bayespd.learn.damage_error) on a regular grid.
Every identity here is exact in the discrete sums, so the tolerances are rounding."""
import numpy as np
import pytest

from bayespd.bonds import find_bonds
from bayespd.discretize import from_points
from bayespd.learn.damage_error import cone_average, lagged, shifted, straight_crack_intact
from bayespd.learn.discrepancy import count_damage

H = 5.0


def grid(n=11):
    g = (np.arange(n) - (n - 1) / 2) * H
    return np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)


def test_lagged_delays_and_advances_by_whole_frames():
    a = np.arange(5.0)[:, None] * np.ones((1, 3))
    np.testing.assert_array_equal(lagged(a, 2)[:, 0], [0, 0, 0, 1, 2])
    np.testing.assert_array_equal(lagged(a, -1)[:, 0], [1, 2, 3, 4, 4])
    np.testing.assert_array_equal(lagged(a, 0), a)


def test_shifted_moves_values_by_a_lattice_vector_and_zeroes_what_comes_in():
    x = grid(5)
    f = np.stack([x[:, 0], x[:, 1]])  # (2, N): two frames
    out = shifted(f, x, [H, 0.0])
    inside = x[:, 0] > x[:, 0].min() + H / 2
    np.testing.assert_allclose(out[0, inside], x[inside, 0] - H, atol=1e-12)
    np.testing.assert_array_equal(out[:, ~inside], 0.0)
    assert not shifted(f, x, [H / 2, 0.0]).any()  # off the lattice: no source node


def test_cone_average_keeps_constants_everywhere_and_linear_fields_inside():
    """Row weights sum to 1 (constants kept to rounding); the weights are symmetric in x_j - x_i,
    so a linear field is kept where the whole cone lies on the grid."""
    x = grid()
    R = 2.6 * H
    np.testing.assert_allclose(cone_average(np.full((3, len(x)), 0.7), x, R), 0.7, rtol=1e-14)
    lin = 0.3 * x[:, 0] - 1.1 * x[:, 1] + 2.0
    inside = np.all(np.abs(x) <= np.abs(x).max() - R, axis=1)
    assert inside.sum() >= 4
    np.testing.assert_allclose(cone_average(lin, x, R)[inside], lin[inside], atol=1e-12)
    with pytest.raises(ValueError, match="radius"):
        cone_average(lin, x, 0.0)


def test_straight_crack_cuts_the_bonds_across_it_and_shifts_with_its_line():
    """Nearest-neighbour bonds: a crack at x = H/2 from y = -H/2 up to y = 2.6 H cuts the horizontal
    bonds at y = 0, H, 2H (3 bonds); no tip (NaN) cuts none. With the horizon's bonds, the eq 5.4
    field of a crack one spacing to the right is the first one shifted by (H, 0) wherever the
    shifted family is complete (the bond set is translation invariant away from the edges)."""
    x = grid()
    particles = from_points(x, np.full(len(x), H * H), h=H)
    near = find_bonds(particles, 1.01 * H)
    i, j = near.i[near.length < 1.01 * H], near.j[near.length < 1.01 * H]  # no partial-volume diagonals
    g = straight_crack_intact(x, i, j, H / 2, -H / 2, [np.nan, 2.6 * H])
    np.testing.assert_array_equal(g[0], 1.0)
    cut = g[1] == 0
    assert cut.sum() == 3
    np.testing.assert_allclose(np.sort(x[i[cut], 1]), [0.0, H, 2 * H])
    b = find_bonds(particles, 2.5 * H)
    delta = 2.5 * H
    phi = [count_damage(len(x), b.i, b.j, b.length, delta, straight_crack_intact(x, b.i, b.j, c, -H / 2, [2.6 * H]))
           for c in (H / 2, 1.5 * H)]
    far = np.all(np.abs(x) <= np.abs(x).max() - 4 * H, axis=1)
    assert phi[1][0, far].max() > 0.3
    np.testing.assert_allclose(shifted(phi[0], x, [H, 0.0])[0, far], phi[1][0, far], atol=1e-15)
