"""Measured fields onto particles: index order, particles at the nodes or interpolated, masks."""
import numpy as np
import pytest
import torch
import xarray as xr

import bayespd as bp

X, Y = np.arange(5.0), 10.0 + np.arange(3.0)  # nx = 5, ny = 3: a non-square grid


def affine(p):
    """An asymmetric field: u = x + 10 y, v = 100 x - y (a transposed read changes it)."""
    return np.stack([p[..., 0] + 10 * p[..., 1], 100 * p[..., 0] - p[..., 1]], axis=-1)


def grids(order):
    xx, yy = np.meshgrid(X, Y, indexing=order)
    f = affine(np.stack([xx, yy], axis=-1))
    return f[..., 0], f[..., 1]


@pytest.mark.parametrize("order", ["xy", "ij", None])
def test_index_order_puts_each_value_at_its_point(order):
    u, v = grids(order or "xy")
    field = bp.from_grid_field(X, Y, u, v, order=order)
    assert field.points.shape == (15, 2)
    assert np.array_equal(field.points[:5, 0], X) and np.all(field.points[:5, 1] == Y[0])  # x fastest
    assert np.array_equal(field.y, affine(field.points))
    assert np.array_equal(field.grid(field.y[:, 0], order or "xy"), u)


def test_named_dims_carry_the_order():
    u, v = grids("ij")
    field = bp.from_grid_field(X, Y, xr.DataArray(u, dims=("x", "y")), xr.DataArray(v, dims=("x", "y")))
    assert np.array_equal(field.y, affine(field.points))
    with pytest.raises(ValueError, match="order 'ij'.*drop order"):
        bp.from_grid_field(X, Y, xr.DataArray(u, dims=("x", "y")), v, order="xy")


def test_ambiguous_or_transposed_layouts_are_refused():
    square = np.zeros((3, 3))
    with pytest.raises(ValueError, match="square 3 x 3 grid.*pass order='xy'"):
        bp.from_grid_field(Y, Y, square, square)
    u, v = grids("xy")
    with pytest.raises(ValueError, match="u has shape \\(3, 5\\) but order='ij'.*transposed"):
        bp.from_grid_field(X, Y, u, v, order="ij")
    with pytest.raises(ValueError, match="order must be 'xy'"):
        bp.from_grid_field(X, Y, u, v, order="yx")


def test_particles_at_the_nodes_observe_exactly_and_solve():
    """Node-centred particles (volume h^2 t), H a selection; a Scene takes them as they are."""
    x, y = 2.0 * np.arange(12), 2.0 * np.arange(6)
    u, v = np.meshgrid(0.01 * x, -0.003 * y, indexing="xy")
    field = bp.from_grid_field(x, y, u, v + 0 * u, thickness=0.5)
    p = field.particles
    assert p.h == 2.0 and np.allclose(p.volume, 2.0)
    assert np.array_equal(p.x, field.points)
    assert np.array_equal(field.observation(torch.as_tensor(field.y)).numpy(), field.y)
    scene = bp.Scene(bp.LPS(p, bp.find_bonds(p, 6.0)), [bp.Dirichlet.layer(p, "left", 6.0)],
                     [bp.Load(p.layer("right", 2.0), (5.0, 0.0))], field.observation)
    assert scene.predict({"K": 100.0, "G": 50.0, "delta": 5.0}).shape == field.y.shape


def test_interpolated_onto_given_particles_is_exact_for_affine_fields():
    """Bilinear interpolation reproduces affine fields; points outside the body are masked."""
    p = bp.grid_2d(6.0, 2.5, 0.5, origin=(-0.5, 9.5))
    u, v = grids("xy")
    field = bp.from_grid_field(X, Y, u, v, particles=p)
    inside = field.valid[:, 0]
    assert np.array_equal(inside, field.points[:, 1] < 12)  # the last particle row is y = 11.75
    predicted = field.observation(torch.as_tensor(affine(p.x))).numpy()
    assert np.abs(predicted[inside] - field.y[inside]).max() < 1e-12


def test_irregular_particles_interpolate_barycentrically(rng):
    p = bp.grid_2d(6.0, 4.0, 0.5, origin=(-0.5, 9.0))
    p = bp.from_points(p.x + 0.05 * rng.uniform(-1, 1, p.x.shape), p.volume, h=0.5)
    u, v = grids("xy")
    field = bp.from_grid_field(X, Y, u, v, particles=p)
    predicted = field.observation(torch.as_tensor(affine(p.x))).numpy()
    assert field.valid.all() and np.abs(predicted - field.y).max() < 1e-9


def test_missing_data_body_edges_and_sigma_masks():
    u, v = grids("xy")
    u[1, 2] = np.nan  # a failed subset at (2, 11): both components masked
    sigma = np.full((3, 5), 0.01)
    sigma[0, 4] = -1.0  # VIC / DICe: correlation failed at (4, 10)
    field = bp.from_grid_field(X, Y, u, v, sigma=sigma, body=lambda x: x[:, 0] != 0.0, edge=0.6)
    assert field.particles.n == 12  # the column x = 0 is not material
    assert not field.valid[7].any() and not field.valid[4].any() and not field.valid[0].any()
    assert field.valid.sum() == 2 * (15 - 3 - 2)
    assert np.array_equal(np.flatnonzero(field.edge.all(axis=1)), [7, 8])  # the others lie 0.5 from an edge
    data = field.data()
    assert torch.equal(data["mask"], torch.as_tensor(field.valid & field.edge))
    assert torch.isfinite(data["y"]).all() and float(data["y"][7].abs().sum()) == 0.0


def test_on_particles_puts_each_measured_value_on_its_particle():
    """Particles at the nodes, a column cut out by ``body``, a failed subset: every particle
    holds the affine field at its own position, the failed one NaN; an interpolating
    observation has no per-particle values and is refused."""
    u, v = grids("xy")
    u[1, 2] = np.nan  # the subset at (2, 11)
    field = bp.from_grid_field(X, Y, u, v, body=lambda x: x[:, 0] != 0.0)
    on = field.on_particles()
    failed = np.all(field.particles.x == (2.0, 11.0), axis=1)
    assert on.shape == (12, 2) and failed.sum() == 1 and np.isnan(on[failed]).all()
    assert np.array_equal(on[~failed], affine(field.particles.x[~failed]))
    with pytest.raises(ValueError, match="interpolate the particles.*particles=None"):
        bp.from_grid_field(X, Y, u, v, particles=bp.grid_2d(6.0, 2.5, 0.5, origin=(-0.5, 9.5))).on_particles()


def test_points_off_a_lattice_need_particles(rng):
    points = rng.uniform(0, 5, (20, 2))
    with pytest.raises(ValueError, match="not on a square lattice.*pass particles="):
        bp.from_point_field(points, np.zeros((20, 2)))
    rect = np.stack(np.meshgrid(np.arange(4.0), 1.5 * np.arange(3.0)), -1).reshape(-1, 2)
    with pytest.raises(ValueError, match="not on a square lattice"):
        bp.from_point_field(rect, np.zeros((12, 2)))


def test_bad_input_is_refused_by_name():
    points = np.stack(np.meshgrid(np.arange(3.0), np.arange(2.0)), -1).reshape(-1, 2)
    ok = np.zeros((6, 2))
    bad = points.copy()
    bad[2, 0] = np.nan
    with pytest.raises(ValueError, match="points contains NaN"):
        bp.from_point_field(bad, ok)
    with pytest.raises(ValueError, match="displacement must be \\(n, dim\\)"):
        bp.from_point_field(points, ok[:4])
    with pytest.raises(ValueError, match="valid must be boolean"):
        bp.from_point_field(points, ok, valid=np.ones(6))
    with pytest.raises(ValueError, match="sigma must have one value per point"):
        bp.from_point_field(points, ok, sigma=np.ones(5))
    with pytest.raises(ValueError, match="edge must lie in"):
        bp.from_point_field(points, ok, edge=-1.0)
    with pytest.raises(ValueError, match="thickness must be positive"):
        bp.from_point_field(points, ok, thickness=0.0)
    with pytest.raises(ValueError, match="with particles= given, cut the body"):
        bp.from_point_field(points, ok, particles=bp.grid_2d(3.0, 2.0, 1.0), body=lambda x: x[:, 0] > 0)
    with pytest.raises(ValueError, match="one measured point gives no lattice spacing"):
        bp.from_point_field(points[:1], ok[:1])
    with pytest.raises(ValueError, match="two measured points fall on one lattice node"):
        bp.from_point_field(np.vstack([points, points[:1] + 1e-5]), np.zeros((7, 2)))
