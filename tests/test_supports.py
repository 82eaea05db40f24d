"""Point supports, rollers, point loads and tractions: where they act and their exact totals."""
import numpy as np
import pytest
import torch

import bayespd as bp


@pytest.fixture
def plate():
    return bp.grid_2d(10.0, 4.0, 0.5, thickness=2.0)


def test_point_support_fixes_the_nearest_particle(plate):
    bc = bp.point_support(plate, (3.1, 0.2), value=(None, 0.0))
    assert np.array_equal(plate.x[bc.mask], [[3.25, 0.25]]) and bc.value == (None, 0.0)
    with pytest.raises(ValueError, match="the support point \\[30.0, 0.0\\] is .* outside the body"):
        bp.point_support(plate, (30.0, 0.0))
    with pytest.raises(ValueError, match="the support point must have 2 coordinates"):
        bp.point_support(plate, (1.0, 1.0, 1.0))


def test_roller_fixes_one_component(plate):
    bc = bp.roller(plate, plate.layer("bottom", 0.5), axis=1, value=-0.01)
    assert bc.value == (None, -0.01) and bc.mask.sum() == 20
    with pytest.raises(ValueError, match="axis must be < 2"):
        bp.roller(plate, bc.mask, axis=2)
    with pytest.raises(ValueError, match="mask must be boolean with one entry per particle"):
        bp.roller(plate, np.ones(3, bool), axis=0)


def test_point_load_total_is_exact(plate):
    force = torch.tensor([3.0, -7.0])
    load = bp.point_load(plate, (5.0, 2.0), force, radius=1.2)
    nodal = load.nodal(plate)
    within = np.linalg.norm(plate.x - [5.0, 2.0], axis=1) <= 1.2
    assert np.array_equal(load.mask, within) and within.sum() > 4
    assert float((nodal.sum(0) - force).abs().max()) < 1e-14 * float(force.abs().max())
    assert bp.point_load(plate, (5.1, 2.1), force).mask.sum() == 1
    with pytest.raises(ValueError, match="no particle lies within radius=0.1"):
        bp.point_load(plate, (5.0, 2.0), force, radius=0.1)
    with pytest.raises(ValueError, match="radius must be positive"):
        bp.point_load(plate, (5.0, 2.0), force, radius=-1.0)


def test_traction_total_is_traction_times_edge_times_thickness(plate, rng):
    t = np.array([12.0, -3.0])  # force per area
    load = bp.traction(plate, "right", t)
    nodal = load.nodal(plate)
    assert np.allclose(plate.x[load.mask, 0], 9.75)  # the outermost column
    assert float((nodal.sum(0) - torch.as_tensor(t * 4.0 * 2.0)).abs().max()) < 1e-12
    top = bp.traction(plate, "top", t, depth=1.0)
    assert float((top.nodal(plate).sum(0) - torch.as_tensor(t * 10.0 * 2.0)).abs().max()) < 1e-12
    # spread by volume: particles of unequal volume carry shares proportional to it
    volume = plate.volume * rng.uniform(0.5, 1.5, plate.n)
    uneven = bp.from_points(plate.x, volume, h=0.5, thickness=2.0)
    f = bp.traction(uneven, "right", t).nodal(uneven).numpy()[load.mask]
    assert np.allclose(f[:, 0] / volume[load.mask], f[0, 0] / volume[load.mask][0], rtol=1e-13)
    with pytest.raises(ValueError, match="side must be one of"):
        bp.traction(plate, "front", t)
    with pytest.raises(ValueError, match="the traction must have 2 components"):
        bp.traction(plate, "left", [1.0])
    with pytest.raises(ValueError, match="the traction contains NaN"):
        bp.traction(plate, "left", [np.nan, 0.0])

