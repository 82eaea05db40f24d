"""Observation operators (particles, bilinear DIC grids) and masks of missing data."""
import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch

import bayespd as bp
from bayespd.observe import (GridObservation, ParticleObservation, edge_mask, finite_mask, grid_points,
                             model_data)
from bayespd.models.elastic_plate import elastic_plate


def bilinear(x, coeffs):
    """u_c = a + b x + c y + d x y for each component's row of coeffs."""
    basis = np.stack([np.ones(len(x)), x[:, 0], x[:, 1], x[:, 0] * x[:, 1]], axis=1)
    return basis @ np.asarray(coeffs).T


COEFFS = [[0.3, -1.2, 0.7, 0.45], [-2.0, 0.25, 1.5, -0.8]]


def test_particle_subset_is_exact(rng):
    p = bp.grid_2d(6.0, 4.0, 1.0)
    u = torch.as_tensor(rng.normal(size=(p.n, 2)))
    mask = p.layer("top", 1.0)
    by_mask, by_index = ParticleObservation(p, mask), ParticleObservation(p, [3, 0, 17])
    assert by_mask.n == 6 and by_index.n == 3
    np.testing.assert_array_equal(by_mask.points, p.x[mask])
    assert torch.equal(by_mask(u), u[torch.as_tensor(mask)])
    assert torch.equal(by_index(u), u[[3, 0, 17]])
    assert by_index.mask.shape == (3, 2) and by_index.mask.all()


@pytest.mark.parametrize("which, match", [
    (np.ones(5, bool), "one entry per particle"),
    ([], "non-empty"),
    ([0, 24], "must lie in"),
    ([1, 2, 1], "repeated"),
])
def test_particle_subset_refuses_bad_selection(which, match):
    with pytest.raises(ValueError, match=match):
        ParticleObservation(bp.grid_2d(6.0, 4.0, 1.0), which)


def test_grid_points_order():
    pts = grid_points((0.25, 1.0), (0.5, 2.0), (3, 2))
    np.testing.assert_array_equal(pts, [[0.25, 1], [0.75, 1], [1.25, 1], [0.25, 3], [0.75, 3], [1.25, 3]])
    with pytest.raises(ValueError, match="positive spacing"):
        grid_points((0, 0), 0.0, (3, 2))


def test_bilinear_grid_reproduces_bilinear_fields_and_masks_missing_corners():
    """Particles at 0.5..5.5 x 0.5..3.5 minus the one at (2.5, 1.5); a DIC grid of 12 x 8
    points from (0.25, 0.25) step 0.5. Valid: the 10 x 6 points between the outer particles,
    minus the 4 x 4 points in the four cells around the missing particle: 44."""
    full = bp.grid_2d(6.0, 4.0, 1.0)
    p = full.where(~np.all(np.isclose(full.x, [2.5, 1.5]), axis=1))
    pts = grid_points((0.25, 0.25), 0.5, (12, 8))
    obs = GridObservation(p, pts)
    inner = np.all((pts >= 0.5) & (pts <= [5.5, 3.5]), axis=1)
    near_hole = np.all(np.abs(pts - [2.5, 1.5]) < 1.0, axis=1)
    expected = inner & ~near_hole
    assert expected.sum() == 44
    np.testing.assert_array_equal(obs.mask, np.repeat(expected[:, None], 2, axis=1))
    y = obs(torch.as_tensor(bilinear(p.x, COEFFS))).numpy()
    np.testing.assert_allclose(y[expected], bilinear(pts[expected], COEFFS), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(y[~expected], 0.0)


def test_grid_point_on_a_boundary_particle_is_that_particle():
    p = bp.grid_2d(6.0, 4.0, 1.0)
    obs = GridObservation(p, [[5.5, 3.5], [0.5, 2.0]])
    u = torch.as_tensor(bilinear(p.x, COEFFS))
    assert obs.mask.all()
    np.testing.assert_allclose(obs(u), bilinear(obs.points, COEFFS), rtol=1e-12, atol=1e-12)


def test_trilinear_grid_in_3d(rng):
    p = bp.grid_3d(3.0, 2.0, 2.0, 0.5)
    pts = rng.uniform(p.x.min(0), p.x.max(0), size=(20, 3))
    field = lambda x: 1 + x[:, 0] - 2 * x[:, 1] + 0.5 * x[:, 2] + x.prod(1) + x[:, 0] * x[:, 2]  # noqa: E731
    y = GridObservation(p, pts)(torch.as_tensor(np.stack([field(p.x)] * 3, axis=1)))
    np.testing.assert_allclose(y[:, 0], field(pts), rtol=1e-12)


def test_grid_observation_names_the_barycentric_alternative(rng):
    p = bp.from_points(rng.uniform(0, 5, size=(40, 2)), np.ones(40))
    with pytest.raises(ValueError, match=r"irregular particle set use the barycentric bp\.Observation"):
        GridObservation(p, [[1.0, 1.0]])


def test_edge_mask_drops_a_band_along_outer_and_hole_edges():
    """Points at the 60 cell centres of a 10 x 6 plate with the cell at (4.5, 2.5) cut out.
    Width 1.2: the outer ring (0.5 from the edge) goes, leaving 8 x 4; around the hole its
    8 neighbours (0.5 and 0.71 away) and the hole centre itself (outside) go: 32 - 9 = 23."""
    full = bp.grid_2d(10.0, 6.0, 1.0)
    hole = np.all(np.isclose(full.x, [4.5, 2.5]), axis=1)
    mask = edge_mask(full.where(~hole), full.x, 1.2)
    assert mask.shape == (60, 2) and np.array_equal(mask[:, 0], mask[:, 1])
    inner = np.all((full.x > 1) & (full.x < [9, 5]), axis=1)
    near_hole = np.all(np.abs(full.x - [4.5, 2.5]) < 1.5, axis=1)
    np.testing.assert_array_equal(mask[:, 0], inner & ~near_hole)
    assert mask[:, 0].sum() == 23
    assert edge_mask(full, full.x, 0.0).all()  # no band: every point inside the body is kept
    assert not edge_mask(full, [[-1.0, 3.0]], 0.0).any()  # outside the body


def test_masks_combine_and_model_data_zero_fills():
    y = np.array([[1.0, np.nan], [3.0, 4.0], [np.inf, 6.0]])
    band = np.array([[True, True], [False, False], [True, True]])
    data = model_data(y, band)
    np.testing.assert_array_equal(finite_mask(y) & band, [[True, False], [False, False], [False, True]])
    np.testing.assert_array_equal(data["mask"].numpy(), finite_mask(y) & band)
    np.testing.assert_array_equal(data["y"].numpy(), [[1.0, 0.0], [0.0, 0.0], [0.0, 6.0]])
    with pytest.raises(ValueError, match="shape of y"):
        model_data(y, band[:, 0])


def test_dic_grid_mask_drives_the_elastic_plate_likelihood():
    """The model's log-likelihood with a DIC grid, a hole and NaN data is the Normal log-density
    summed over the observed entries only, and its gradient is finite (no NaN leaks through)."""
    full = bp.grid_2d(8.0, 4.0, 1.0)
    p = full.where(~np.all(np.isclose(full.x, [4.5, 1.5]), axis=1))
    obs = GridObservation(p, grid_points((0.3, 0.3), 0.8, (10, 5)))
    scene = bp.Scene(bp.LPS(p, bp.find_bonds(p, 2.5)), [bp.Dirichlet.layer(p, "left", 2.5)],
                     [bp.Load(p.layer("right", 1.0), (10.0, 0.0))], obs)
    params = {"K": torch.tensor(3000.0, requires_grad=True), "G": torch.tensor(1400.0), "delta": torch.tensor(2.2)}
    with torch.no_grad():
        clean = scene.observe(scene.solve(params))
    y = clean.numpy() * 1.01
    y[np.flatnonzero(obs.mask[:, 0])[:3], 1] = np.nan
    data = model_data(y, obs.mask & edge_mask(p, obs.points, 1.2))
    assert 0 < int(data["mask"].sum()) < obs.mask.sum() - 3
    model = pyro.condition(elastic_plate(scene, {"K": 3000.0, "G": 1400.0}, 0.01),
                           {**params, "sigma": torch.tensor(0.001)})
    trace = pyro.poutine.trace(model).get_trace(**data)
    site = trace.nodes["y"]
    logp = site["fn"].log_prob(site["value"]).sum()
    mean = scene.observe(scene.solve(params)).detach()
    observed = data["mask"]
    expected = dist.Normal(mean[observed], 0.001).log_prob(torch.as_tensor(y)[observed]).sum()
    torch.testing.assert_close(logp, expected, rtol=1e-12, atol=0)
    logp.backward()
    assert torch.isfinite(params["K"].grad) and params["K"].grad != 0


def test_opening_is_the_difference_of_the_two_faces(small_scene):
    """An opening observation of u is u(above) - u(below): zero for a rigid translation,
    exact for an affine field (barycentric interpolation reproduces it)."""
    p = small_scene.particles
    x0 = p.x.mean(0)
    above = x0 + np.array([[0.0, 0.5], [2.0, 0.5]])
    below = above - np.array([0.0, 1.0])
    obs = bp.OpeningObservation(p, above, below, component=1)
    F = torch.tensor([[1e-3, 2e-3], [-1e-3, 4e-3]], dtype=torch.float64)
    u = torch.as_tensor(p.x) @ F.T + torch.tensor([0.3, -0.2], dtype=torch.float64)
    np.testing.assert_allclose(obs(u).numpy(), np.tile([2e-3, 4e-3], (2, 1)), atol=1e-14)
    assert obs.mask[:, 1].all() and not obs.mask[:, 0].any()
    with pytest.raises(ValueError, match="matching"):
        bp.OpeningObservation(p, above, below[:1])


def test_an_observation_of_no_points_is_refused():
    p = bp.grid_2d(4.0, 3.0, 1.0)
    for make in (bp.Observation, GridObservation):
        with pytest.raises(ValueError, match="the observation has no points"):
            make(p, np.zeros((0, 2)))
    with pytest.raises(ValueError, match="none of the 2 points can be interpolated.*units and origin"):
        GridObservation(p, [[40.0, 30.0], [-5.0, 1.0]])
    one = GridObservation(p, [[1.5, 1.5]])  # one point suffices
    np.testing.assert_allclose(one(torch.as_tensor(p.x)), [[1.5, 1.5]], rtol=1e-12)


def test_grid_points_refuse_non_finite_origin_and_spacing():
    with pytest.raises(ValueError, match="spacing contains NaN or inf"):
        grid_points((0.0, 0.0), np.inf, (2, 2))
    with pytest.raises(ValueError, match="origin contains NaN or inf"):
        grid_points((np.nan, 0.0), 1.0, (2, 2))
    np.testing.assert_allclose(grid_points((0.0, 0.0), 1e-300, (2, 1)), [[0.0, 0.0], [1e-300, 0.0]], rtol=0)


def test_edge_mask_refuses_a_negative_or_infinite_width():
    p = bp.grid_2d(4.0, 3.0, 1.0)
    with pytest.raises(ValueError, match=r"width must lie in \[0, inf\), got -1"):
        edge_mask(p, p.x, -1.0)
    with pytest.raises(ValueError, match="width contains NaN or inf"):
        edge_mask(p, p.x, np.inf)
