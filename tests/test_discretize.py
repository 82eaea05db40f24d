"""bayespd/discretize.py: cell-centred grids (positions, volumes that sum to the body's),
bounding boxes, region masks, arbitrary points, refused particle sets."""
import numpy as np
import pytest

import bayespd as bp


def test_grid_2d_is_cell_centred_and_its_volumes_sum_to_the_body():
    """[0, 6] x [0, 4] at h = 0.5, thickness 2: 12 x 8 centres at (k + 1/2) h, x fastest; each
    volume h^2 t, summing to L W t = 48 exactly; the bounding box is the body."""
    p = bp.grid_2d(6.0, 4.0, 0.5, thickness=2.0, origin=(1.0, -1.0))
    assert p.n == 96 and p.dim == 2 and p.h == 0.5 and p.thickness == 2.0
    np.testing.assert_array_equal(p.x[:3], [[1.25, -0.75], [1.75, -0.75], [2.25, -0.75]])
    np.testing.assert_array_equal(p.x[12], [1.25, -0.25])
    assert np.all(p.volume == 0.5) and p.volume.sum() == 48.0
    np.testing.assert_array_equal(p.lower(), [1.0, -1.0])
    np.testing.assert_array_equal(p.upper(), [7.0, 3.0])


def test_grid_3d_volumes_and_box():
    p = bp.grid_3d(2.0, 1.0, 1.5, 0.5)
    assert p.n == 4 * 2 * 3 and p.dim == 3 and p.thickness == 1.0
    assert p.volume.sum() == pytest.approx(3.0, rel=1e-15)
    np.testing.assert_array_equal(p.lower(), [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(p.upper(), [2.0, 1.0, 1.5])
    assert len(np.unique(p.x, axis=0)) == p.n


def test_layers_boxes_and_regions():
    """A layer of depth d along a side holds the cells whose centres lie closer than d to it
    (d = 1: one column or row, d = 2.5: two);
    ``box`` is closed; ``region`` takes a vectorised predicate; ``where`` keeps the rest."""
    p = bp.grid_2d(10.0, 6.0, 1.0)
    for side, count in (("left", 6), ("right", 6), ("bottom", 10), ("top", 10)):
        assert p.layer(side, 1.0).sum() == count and p.layer(side, 2.5).sum() == 2 * count
    assert np.all(p.x[p.layer("right", 2.0), 0] > 8.0)
    assert p.box((0.5, 0.5), (2.5, 1.5)).sum() == 6  # closed: centres on the faces count
    disc = p.region(lambda x: np.hypot(x[:, 0] - 5, x[:, 1] - 3) < 1.0)
    assert disc.sum() == 4
    holed = p.where(~disc)
    assert holed.n == 56 and holed.h == p.h and holed.volume.sum() == 56.0
    q = bp.grid_3d(2.0, 2.0, 3.0, 1.0)
    assert q.layer("back", 1.0).sum() == 4 and np.all(q.x[q.layer("front", 1.0), 2] == 0.5)


def test_bad_masks_and_sides():
    p = bp.grid_2d(4.0, 4.0, 1.0)
    with pytest.raises(ValueError, match="side must be one of"):
        p.layer("front", 1.0)
    with pytest.raises(ValueError, match="removes every particle"):
        p.where(np.zeros(p.n, bool))
    with pytest.raises(ValueError, match="one boolean per particle"):
        p.region(lambda x: x[:3, 0] > 0)
    with pytest.raises(ValueError, match="multiple of h"):
        bp.grid_2d(4.0, 4.3, 1.0)
    with pytest.raises(ValueError, match="must be positive"):
        bp.grid_2d(4.0, 4.0, -1.0)


def test_from_points_keeps_positions_volumes_and_the_given_spacing():
    """Arbitrary points are kept as given; h defaults to sqrt(median(V) / t) in 2D and
    cbrt(median V) in 3D."""
    x = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [3.0, 1.0]])
    V = np.array([1.0, 4.0, 9.0, 16.0])
    p = bp.from_points(x, V, thickness=2.0)
    np.testing.assert_array_equal(p.x, x)
    np.testing.assert_array_equal(p.volume, V)
    assert p.h == pytest.approx(np.sqrt(6.5 / 2.0), rel=1e-15)
    assert bp.from_points(x, V, h=0.7).h == 0.7


@pytest.mark.parametrize("x, volume, match", [
    ([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]], [1.0, 1.0, 1.0], "closer than 1e-6 h.*remove duplicate"),
    ([[0.0, 0.0], [1.0, 0.0]], [1.0, 0.0], "zero or negative volume"),
    ([[0.0, 0.0], [1.0, 0.0]], [1.0, -2.0], "zero or negative volume"),
    ([[0.0, np.nan], [1.0, 0.0]], [1.0, 1.0], "NaN or inf"),
    ([[0.0, 0.0], [1.0, 0.0]], [1.0, np.inf], "NaN or inf"),
    ([[0.0, 0.0], [1.0, 0.0]], [1.0], "one entry per particle"),
])
def test_bad_particle_sets(x, volume, match):
    with pytest.raises(ValueError, match=match):
        bp.from_points(x, volume)


def test_from_points_spacing_from_volumes():
    p = bp.from_points(bp.grid_3d(2.0, 2.0, 2.0, 0.5).x, np.full(64, 0.125))
    assert p.h == pytest.approx(0.5) and p.dim == 3


def test_particles_closer_than_1e_6_h_are_duplicates():
    x = np.array([[0.0, 0.0], [1.0, 0.0], [1.0 + 1e-7, 0.0]])
    with pytest.raises(ValueError, match=r"1 pair\(s\) of particles are closer than 1e-6 h.*remove duplicate"):
        bp.from_points(x, np.ones(3), h=1.0)
    near = bp.from_points(x + [[0.0, 0.0], [0.0, 0.0], [1e-5, 0.0]], np.ones(3), h=1.0)  # 1e-5 h: kept
    assert near.n == 3


@pytest.mark.parametrize("extent, h, match", [
    ((np.inf, 2.0), 1.0, "box extents contains NaN or inf"),
    ((4.0, 2.0), np.nan, "h contains NaN or inf"),
    ((4.0, 2.0), -1.0, "h must be positive, got -1"),
])
def test_grid_of_non_finite_extent_or_spacing(extent, h, match):
    with pytest.raises(ValueError, match=match):
        bp.grid_2d(*extent, h)


def test_infinite_spacing_is_refused():
    with pytest.raises(ValueError, match="the particle spacing h contains NaN or inf"):
        bp.Particles(np.zeros((1, 2)), np.ones(1), np.inf)
