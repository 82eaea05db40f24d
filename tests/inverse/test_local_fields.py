"""``bayespd.inverse.local_fields``: the local VFM's default fields (a harmonic load field and
bilinear hats) and the hole staircase they keep away from."""
import numpy as np
from scipy.spatial import cKDTree

import bayespd as bp
from bayespd.inverse.local_fields import harmonic_load_field, local_fields, rough_boundary
from tests.inverse.test_vfm_local import holed_plate


def test_rough_boundary_is_the_hole_staircase_only():
    p = holed_plate().particles
    rough = rough_boundary(p)
    r = np.linalg.norm(p.x - [20.0, 10.0], axis=1)
    assert rough.sum() > 8 and np.all(r[rough] < 4.0 + 1.5)  # within a cell diagonal of the circle
    assert not rough_boundary(bp.grid_2d(10.0, 5.0, 1.0)).any()  # straight edges and corners


def test_harmonic_load_field_obeys_its_constraints_and_the_maximum_principle():
    """0 near the clamp, 1 near the load, one constant on the hole's zone, discrete-harmonic
    elsewhere (4-neighbour Laplacian 0 to round-off), values in [0, 1]."""
    scene = holed_plate()
    p, margin = scene.particles, 2.0
    s = harmonic_load_field(scene, margin)(p.x)[:, 0]
    d = lambda m: cKDTree(p.x[m]).query(p.x)[0]  # noqa: E731
    fixed, loaded = scene.constraints.fixed_particles, (scene.force.abs().sum(1) > 0).numpy()
    zero, one, zone = d(fixed) <= margin, d(loaded) <= margin, d(rough_boundary(p)) <= margin
    assert np.all(s[zero] == 0) and np.all(s[one] == 1) and np.ptp(s[zone]) < 1e-12
    assert 0.2 < s[zone][0] < 0.8 and s.min() >= -1e-12 and s.max() <= 1 + 1e-12
    tree = cKDTree(p.x)
    pairs = tree.query_pairs(1.0 + 1e-9, output_type="ndarray")
    lap = np.zeros(p.n)
    np.add.at(lap, pairs[:, 0], s[pairs[:, 1]] - s[pairs[:, 0]])
    np.add.at(lap, pairs[:, 1], s[pairs[:, 0]] - s[pairs[:, 1]])
    free = ~(zero | one | zone)
    assert np.abs(lap[free]).max() < 1e-10


def test_hats_keep_off_supports_loads_and_holes():
    scene = holed_plate()
    p = scene.particles
    fields = local_fields(scene, margin=2.0, size=4.0)
    avoid = scene.constraints.fixed_particles | (scene.force.abs().sum(1) > 0).numpy() | rough_boundary(p)
    for f in fields[1:]:
        assert not np.any(f(p.x)[avoid])
    assert len(fields) > 10
