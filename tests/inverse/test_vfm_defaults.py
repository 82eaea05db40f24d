"""``bayespd.inverse.vfm_defaults``: interior fields, (m, rule) by the least VFM residual,
and the exactly determined case refused or flagged (FE-field accuracy: the slow tests)."""
import warnings

import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.inverse import virtual_fields as vf
from bayespd.inverse.vfm import ExactlyDeterminedWarning, VirtualWork, identify
from bayespd.inverse.vfm_defaults import estimate, interior_fields, with_rule

TRUTH = {"K": 3000.0, "G": 1400.0}


def plate(rule="linear", h=1.0):
    """A 40 x 24 plate clamped on the left, pulled and sheared on the right, bonds at 3 h."""
    p = bp.grid_2d(40.0, 24.0, h)
    mat = bp.LPS(p, bp.find_bonds(p, 3 * h, rule), plane="stress")
    return bp.Scene(mat, [bp.Dirichlet.layer(p, "left", 3 * h)], [bp.Load(p.layer("right", h), (30.0, 10.0))])


@pytest.mark.parametrize("m,rule", [(2, "smooth"), (3, "linear")])
def test_the_model_that_made_the_data_has_zero_residual_and_is_chosen(m, rule):
    """Same-model data: at the generating (m, rule) the field is an exact equilibrium, so
    Phi = 0 to round-off and the closed form is exact; every other candidate has Phi > 0."""
    scene = plate()
    with torch.no_grad():
        u = with_rule(scene, rule, 3.0).solve(dict(TRUTH, delta=float(m)))
    res = estimate(scene, u, work="pd", ms=(2, 3))
    assert (res.extra["m"], res.extra["rule"], res.extra["delta"]) == (m, rule, float(m))
    assert res.phi < 1e-10 and res.extra["fields"] > 2
    others = [c["phi"] for c in res.extra["candidates"] if (c["m"], c["rule"]) != (m, rule)]
    assert len(others) == 3 and min(others) > 1e3 * res.phi
    for k, v in TRUTH.items():
        assert res.params[k] == pytest.approx(v, rel=1e-8)


def test_interior_bumps_keep_clear_of_edges_loads_and_supports():
    scene = plate()
    fields = interior_fields(scene, 7.0)
    x = scene.particles.x
    clamp_or_load = scene.constraints.fixed_particles | (scene.force.abs().sum(1) > 0).numpy()
    edge = (x[:, 0] < 7) | (x[:, 0] > 33) | (x[:, 1] < 7) | (x[:, 1] > 17)
    for f in fields[1:]:
        v = np.abs(f(x)).sum(1)
        assert not np.any(v[edge | clamp_or_load])
    assert len(fields) >= 3 and np.allclose(fields[0](x)[clamp_or_load & (x[:, 0] > 20)], [30, 10] / np.hypot(30, 10))


def test_two_fields_are_flagged_and_cannot_choose():
    scene = plate()
    with torch.no_grad():
        u = scene.solve(dict(TRUTH, delta=3.0))
    two = vf.interior_bumps((0, 0), (40, 24), (1, 1), 8.0)
    with pytest.warns(ExactlyDeterminedWarning, match="exactly determined.*add fields"):
        identify(VirtualWork(scene, [interior_fields(scene, 8.0)[0], two[0]], {"delta": 3.0}), u)
    with pytest.raises(ValueError, match="exactly determined.*at least three fields"):
        estimate(scene, u, fields=two, ms=(2, 3))


@pytest.mark.parametrize("kw,match", [({"work": "pd", "ms": (0, 2)}, "ms entry must be an integer >= 1"),
                                      ({"work": "pd", "rules": ("cubic",)}, "rules a subset of"),
                                      ({"work": "pd", "clearance": -1.0}, "clearance must be positive"),
                                      ({"work": "pd", "size": 0.0}, "size must be positive"),
                                      ({"size": 0.0}, "size must be positive"),
                                      ({"margin": -1.0}, "margin must be positive"),
                                      ({"work": "fem"}, "work must be 'local'")])
def test_bad_candidates_are_refused_by_name(kw, match):
    scene = plate()
    with pytest.raises(ValueError, match=match):
        estimate(scene, torch.zeros(scene.particles.n, 2), **kw)


@pytest.mark.slow
@pytest.mark.parametrize("nu", [0.2, 0.3, 0.37])
def test_fe_beam_moduli_within_half_a_percent(nu):
    """scikit-fem Q2 plane-stress field of the three-point-bending beam (h_FE = 0.5 mm), PD grid
    h = 0.5 mm: Delorme 2018's load field (cleared off the patches) and 6 interior bumps, (m,
    rule) chosen by the residual: K and G within 0.5 % (the lattice's anisotropy at the
    chosen m bounds the error, bayespd.reference.lattice)."""
    from bayespd.reference import three_point_bending as tpb
    h = 0.5
    fe = tpb.fe_solution(**tpb.REFERENCE_MESH, nu=nu)
    scene = tpb.pd_scene(h, 2 * h)
    paper = vf.bending_fields(tpb.LENGTH, tpb.WIDTH, tpb.SPAN, origin=(tpb.LENGTH / 2, 0),
                              clear_half_width=tpb.PATCH_WIDTH / 2, clear_depth=tpb.PATCH_DEPTH)
    fields = paper[:1] + vf.interior_bumps((0, 0), (tpb.LENGTH, tpb.WIDTH), (6, 1), 2 * 5 * h + 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ExactlyDeterminedWarning)
        res = estimate(scene, torch.as_tensor(fe.at(scene.particles.x)), fields=fields, work="pd", ms=(3, 4, 5))
    truth = tpb.params(1.0, nu)
    assert abs(res.params["K"] / truth["K"] - 1) < 5e-3 and abs(res.params["G"] / truth["G"] - 1) < 5e-3
