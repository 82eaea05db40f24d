"""Bad input is refused early with a ValueError whose message names the fix."""
import numpy as np
import pytest
import torch

import bayespd as bp


@pytest.fixture(scope="module")
def plate():
    p = bp.grid_2d(10.0, 6.0, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 2.5))
    scene = bp.Scene(mat, [bp.Dirichlet.layer(p, "left", 2.5)], [bp.Load(p.layer("right", 1.0), (1.0, 0.0))])
    return p, mat, scene


@pytest.mark.parametrize("params, match", [
    ({"K": -1.0, "G": 1.0, "delta": 2.0}, "K must be positive"),
    ({"K": float("nan"), "G": 1.0, "delta": 2.0}, "K contains NaN"),
    ({"K": 1.0, "G": 0.0, "delta": 2.0}, "G must be positive"),
    ({"K": 1.0, "G": 1.0, "delta": 0.5}, "smaller than the grid spacing"),
    ({"K": 1.0, "G": 1.0, "delta": 3.0}, "larger delta_max"),
    ({"K": 1.0, "G": 1.0}, "missing \\['delta'\\]"),
])
def test_bad_params(plate, params, match):
    with pytest.raises(ValueError, match=match):
        plate[2].solve(params)


def test_per_particle_field_of_wrong_length(plate):
    with pytest.raises(ValueError, match="one value per particle"):
        plate[2].solve({"K": torch.ones(3), "G": 1.0, "delta": 2.0})


def test_thin_dirichlet_layer(plate):
    p, mat, _ = plate
    with pytest.warns(UserWarning, match="at least one horizon thick"):
        bp.Scene(mat, [bp.Dirichlet.layer(p, "left", 1.0)], [bp.Load(p.layer("right", 1.0), (1.0, 0.0))])


def test_observations_outside_body(plate):
    p = plate[0]
    with pytest.raises(ValueError, match="outside the body"):
        bp.Observation(p, [[5.0, 3.0], [50.0, 3.0]])
    holed = p.where(~p.box((4.2, 2.2), (5.8, 3.8)))  # a 2 x 2 hole
    with pytest.raises(ValueError, match="outside the body"):
        bp.Observation(holed, [[5.0, 3.0]])
    obs = bp.Observation(holed, [[3.25, 1.5]])  # inside the material: linear interpolation
    u = torch.as_tensor(holed.x) @ torch.tensor([[1.0, 2.0], [3.0, 4.0]]).T
    np.testing.assert_allclose(obs(u), [[3.25 + 2 * 1.5, 3 * 3.25 + 4 * 1.5]], rtol=1e-12)


def test_isolated_particle_has_empty_family():
    p = bp.grid_2d(6.0, 4.0, 1.0)
    lonely = bp.from_points(np.vstack([p.x, [[20.0, 20.0]]]), np.append(p.volume, 1.0))
    mat = bp.BondBased(lonely, bp.find_bonds(lonely, 2.0))
    with pytest.raises(ValueError, match="particle 24 .* empty family"):
        mat.stiffness({"K": 1.0, "delta": 2.0})


def test_moduli_beyond_the_float64_range_are_refused(plate):
    """K = 1e-300 solved to a displacement 5x off, K = 1e200 overflowed the stiffness."""
    for K in (1e-300, 1e200):
        with pytest.raises(ValueError, match=r"K=1e[-+]?\d+ lies outside \[1e-100, 1e\+100\]: .*rescale the units"):
            plate[2].solve({"K": K, "G": 1.0, "delta": 2.0})


def test_an_overflowing_displacement_is_refused(plate):
    """|u| ~ load / K ~ 1e340 cannot be a float64 whatever the factorisation (LU or CHOLMOD)."""
    with pytest.raises(ValueError, match="displacement overflowed .* load factor params\\['load'\\]"):
        plate[2].solve({"K": 1e-90, "G": 1e-90, "delta": 2.0, "load": 1e250})


def test_coordinates_whose_squares_overflow_are_refused():
    x = bp.grid_2d(4.0, 2.0, 1.0).x.copy()
    x[0, 0] = 1e300
    with pytest.raises(ValueError, match="largest \\|x\\| 1e\\+300.*rescale the units"):
        bp.from_points(x, np.ones(8), h=1.0)


def test_types_masks_thickness_and_zero_loads_are_named(plate):
    p, mat, scene = plate
    with pytest.raises(TypeError, match="the load: expected numbers"):
        bp.Load(p.layer("right", 1.0), "ab")
    with pytest.raises(TypeError, match="params\\['K'\\] must be a number"):
        scene.solve({"K": "soft", "G": 1.0, "delta": 2.0})
    with pytest.raises(TypeError, match="the observation points: expected numbers"):
        bp.Observation(p, "abc")
    with pytest.raises(ValueError, match="load region's mask has shape \\(3,\\)"):
        bp.Scene(mat, scene.dirichlet, [bp.Load(np.ones(3, bool), (1.0, 0.0))])
    with pytest.raises(ValueError, match="Dirichlet region's mask has shape \\(3,\\)"):
        bp.Scene(mat, [bp.Dirichlet(np.ones(3, bool))], scene.loads)
    with pytest.raises(ValueError, match="nothing loads"):
        bp.Scene(mat, scene.dirichlet, [bp.Load(p.layer("right", 1.0), (0.0, 0.0))])
    with pytest.raises(ValueError, match="the thickness must be positive"):
        bp.grid_2d(4.0, 2.0, 1.0, thickness=0.0)
    with pytest.raises(ValueError, match="more than 1e7 cells"):
        bp.grid_2d(4.0, 2.0, 1e-200)
