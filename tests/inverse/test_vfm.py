"""PD Virtual Fields Method (Delorme 2018): patch tests on PD-generated fields (same model ->
exact moduli), closed form vs optimiser, linearity in the PD constants, bad input."""
import warnings

import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.inverse import virtual_fields as vf
from bayespd.inverse.vfm import (PrescribedMismatchWarning, VirtualWork, identify, moduli_from_constants,
                                 optimise, pd_constants)
from bayespd.reference import three_point_bending as tpb
from tests.conftest import plate_scene

H, DELTA = 2.0, 6.0  # coarse beam: 1024 particles


def beam_fields(delta=DELTA):
    """Delorme 2018's two fields, cleared off the support patches, plus interior bumps."""
    paper = vf.bending_fields(tpb.LENGTH, tpb.WIDTH, tpb.SPAN, origin=(tpb.LENGTH / 2, 0),
                              clear_half_width=tpb.PATCH_WIDTH / 2, clear_depth=tpb.PATCH_DEPTH)
    return paper + vf.interior_bumps((0, 0), (tpb.LENGTH, tpb.WIDTH), (2, 1), 2 * delta + 1)


@pytest.fixture(scope="module")
def beam():
    scene = tpb.pd_scene(H, DELTA)
    truth = tpb.params(DELTA)
    u = scene.solve(truth).detach()
    return scene, truth, u


def rel(a, b):
    return abs(a / b - 1)


@pytest.mark.parametrize("n_fields", [2, 6])
def test_closed_form_exact_on_pd_field(beam, n_fields):
    scene, truth, u = beam
    work = VirtualWork(scene, beam_fields()[:n_fields], {"delta": DELTA})
    assert work.linear
    res = identify(work, u)
    assert rel(res.params["K"], truth["K"]) < 1e-10 and rel(res.params["G"], truth["G"]) < 1e-10
    assert res.phi < 1e-12 and res.evaluations == 0
    # the external work of Delorme 2018 eq 31 for the cleared field: F (S/2 - a - mean |x1|)
    assert float(work.external[0]) == pytest.approx(tpb.FORCE * (tpb.SPAN / 2 - 2.0 - 1.0), rel=1e-12)


def test_closed_form_exact_plane_strain():
    scene = plate_scene(nx=14, ny=8, delta_max=2.5, plane="strain")
    truth = {"K": 3000.0, "G": 1400.0}
    u = scene.solve(dict(truth, delta=2.5)).detach()
    fields = [lambda x: np.stack([np.maximum(x[:, 0] - 2.5, 0), 0 * x[:, 0]], 1),
              lambda x: np.stack([0 * x[:, 0], np.maximum(x[:, 0] - 2.5, 0) * x[:, 1]], 1),
              lambda x: np.stack([np.maximum(x[:, 0] - 2.5, 0) ** 2 * x[:, 1], 0 * x[:, 0]], 1)]
    res = identify(VirtualWork(scene, fields, {"delta": 2.5}), u)
    assert rel(res.params["K"], truth["K"]) < 1e-10 and rel(res.params["G"], truth["G"]) < 1e-10


def test_measured_values_on_supports_are_kept_so_rigid_motion_changes_nothing(beam):
    """K annihilates rigid motion, so W*_int = -(K u*)^T u is the same for u and u + r when
    the measured field is used everywhere. Overwriting the supports with their prescribed
    zeros (the former behaviour) put a jump of size |r| there and biased K and G."""
    scene, truth, u = beam
    x = torch.as_tensor(scene.particles.x)
    scale = float(u.abs().max())
    theta = 0.3 * scale / tpb.LENGTH  # a small rotation about the beam's corner
    rigid = torch.stack([0.2 * scale - theta * x[:, 1], -0.5 * scale + theta * x[:, 0]], 1)
    work = VirtualWork(scene, beam_fields(), {"delta": DELTA})
    with pytest.warns(PrescribedMismatchWarning, match="differs from the prescribed one"):
        res = identify(work, u + rigid)
    assert rel(res.params["K"], truth["K"]) < 1e-9 and rel(res.params["G"], truth["G"]) < 1e-9
    # unmeasured constrained dofs are filled with the prescribed values: still exact
    fixed = ~np.asarray(scene.constraints.free_mask).reshape(u.shape)
    res = identify(work, u, observed=~fixed)
    assert rel(res.params["K"], truth["K"]) < 1e-10 and rel(res.params["G"], truth["G"]) < 1e-10


def test_mismatch_within_the_noise_is_not_flagged(beam):
    scene, truth, u = beam
    work = VirtualWork(scene, beam_fields(), {"delta": DELTA})
    noisy = u + 1e-4 * torch.as_tensor(np.random.default_rng(1).standard_normal(u.shape))
    with warnings.catch_warnings():
        warnings.simplefilter("error", PrescribedMismatchWarning)
        work.data(noisy, sigma=1e-4)  # 4 sigma covers the support particles' noise here
    with pytest.warns(PrescribedMismatchWarning, match="4 sigma"):
        work.data(noisy + 1e-3, sigma=1e-4)
    with pytest.raises(ValueError, match="sigma must be the noise sd"):
        work.data(noisy, sigma=-1.0)


def test_optimiser_agrees_with_closed_form_on_noisy_data(beam):
    """With six fields and noise the residual does not vanish: both must find the same
    least-squares minimiser of eq 25 (closed form over (a_s, a_d), optimiser over log K, G)."""
    scene, truth, u = beam
    noisy = u + 2e-3 * torch.as_tensor(np.random.default_rng(0).standard_normal(u.shape))
    work = VirtualWork(scene, beam_fields(), {"delta": DELTA})
    closed = identify(work, noisy)
    opt = optimise(work, noisy, {"K": 5000.0, "G": 5000.0})
    assert closed.phi > 1e-6  # a genuine least-squares problem
    for k in "KG":
        assert rel(opt.params[k], closed.params[k]) < 1e-8, (k, opt.params[k], closed.params[k])
    assert opt.phi == pytest.approx(closed.phi, rel=1e-8)
    assert 0 < opt.evaluations < 100


def test_internal_work_linear_in_pd_constants(beam):
    """W*_int(a) through the general autograd path is linear in (a_s, a_d), and not in (K, G)."""
    scene, truth, u = beam
    work = VirtualWork(scene, beam_fields(), {"delta": DELTA})
    mat = scene.material
    p1, p2 = (3000.0, 1200.0), (4500.0, 2000.0)
    a1, a2 = (np.array([float(c) for c in pd_constants(mat, *p)]) for p in (p1, p2))
    lam, mu = 0.3, 0.9
    K3, G3 = moduli_from_constants(mat, *(lam * a1 + mu * a2))
    W = [work.internal(u, {"K": torch.tensor(K), "G": torch.tensor(G)}).detach().numpy()
         for K, G in (p1, p2, (K3, G3))]
    np.testing.assert_allclose(W[2], lam * W[0] + mu * W[1], rtol=1e-10, atol=1e-10 * np.abs(W[0]).max())
    # plane stress: the same combination of (K, G) is not the same combination of the works
    Kl, Gl = lam * np.array(p1) + mu * np.array(p2)
    Wl = work.internal(u, {"K": torch.tensor(Kl), "G": torch.tensor(Gl)}).detach().numpy()
    combined = lam * W[0] + mu * W[1]
    assert np.max(np.abs(Wl - combined) / np.abs(combined)) > 1e-3
    # the closed-form matrix gives the same works as the general path
    A = work.internal_matrix(u).numpy()
    np.testing.assert_allclose(A @ a1, W[0], rtol=1e-9, atol=1e-9 * np.abs(W[0]).max())


@pytest.mark.parametrize("plane, dim", [("stress", 2), ("strain", 2), ("stress", 3)])
def test_constants_round_trip(plane, dim):
    p = bp.grid_2d(4, 4, 1.0) if dim == 2 else bp.grid_3d(3, 3, 3, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 1.5), plane=plane)
    a_s, a_d = pd_constants(mat, 3333.3, 1538.5)
    assert moduli_from_constants(mat, float(a_s), float(a_d)) == pytest.approx((3333.3, 1538.5), rel=1e-12)
    with pytest.raises(ValueError, match="no positive"):
        moduli_from_constants(mat, float(a_s), -float(a_d))


def test_refuses_a_bond_based_material():
    scene = plate_scene(material="pmb")
    with pytest.raises(ValueError, match="VFM identifies the state-based.*BondBased.*bayespd.LPS"):
        VirtualWork(scene, [lambda x: np.zeros_like(x)], {"delta": 2.5})


def test_refuses_field_not_vanishing_on_supports(beam):
    scene, _, _ = beam
    paper = vf.delorme_fields(tpb.LENGTH, tpb.WIDTH, tpb.SPAN, origin=(tpb.LENGTH / 2, 0))
    with pytest.raises(ValueError, match="not kinematically admissible.*clear_half_width"):
        VirtualWork(scene, paper, {"delta": DELTA})


def test_coverage_refuses_missing_data_only_where_needed(beam):
    scene, truth, u = beam
    bump = vf.bump((64.0, 16.0), (10.0, 5.0), 1)  # non-zero on |x - 64| < 10, |y - 16| < 5
    work = VirtualWork(scene, beam_fields()[:1] + [bump], {"delta": DELTA})
    x = scene.particles.x
    # data missing far (> 2 delta) from where field 1 strains, but field 0 needs them
    far = (np.abs(x[:, 0] - 64) > 10 + 2 * DELTA + H)
    with pytest.raises(ValueError, match="virtual field 0 needs the displacement"):
        identify(work, u, observed=~far)
    # field 1 alone does not need them: its works are unchanged with the data set to NaN
    only_bump = VirtualWork(scene, [bump], {"delta": DELTA})
    holey = u.clone()
    holey[torch.as_tensor(far)] = float("nan")
    np.testing.assert_allclose(only_bump.internal_matrix(only_bump.data(holey)).numpy(),
                               only_bump.internal_matrix(only_bump.data(u)).numpy(), rtol=1e-12)
    # data missing inside the bump's reach: refused, naming the field
    near = np.abs(x[:, 0] - 64) < 1.5  # the two columns at x = 63, 65
    with pytest.raises(ValueError, match="virtual field 0 needs the displacement"):
        only_bump.data(u, observed=~near)


def test_refuses_fields_without_external_work(beam):
    scene, _, u = beam
    work = VirtualWork(scene, vf.interior_bumps((0, 0), (tpb.LENGTH, tpb.WIDTH), (2, 1), 13.0),
                       {"delta": DELTA})
    with pytest.raises(ValueError, match="no virtual field does work"):
        identify(work, u)


def test_optimiser_handles_surface_corrected_material():
    """The general case: the surface correction makes K non-linear in (a_s, a_d), so the
    closed form refuses and the optimiser recovers the moduli exactly (same model)."""
    scene = tpb.pd_scene(4.0, 8.0, surface_correction=True)
    truth = tpb.params(8.0)
    u = scene.solve(truth).detach()
    work = VirtualWork(scene, beam_fields()[:2], {"delta": 8.0})
    assert not work.linear
    with pytest.raises(ValueError, match="use vfm.optimise"):
        identify(work, u)
    res = optimise(work, u, {"K": 5000.0, "G": 5000.0})
    assert rel(res.params["K"], truth["K"]) < 1e-8 and rel(res.params["G"], truth["G"]) < 1e-8


@pytest.mark.slow
def test_fe_field_h05_m5_within_model_error():
    """FE (scikit-fem) data, no inverse crime: PD-VFM at h = 0.5, m = 5 lands within the
    PD-vs-FE model error measured by experiments/vfm_three_point_bending.py."""
    fe = tpb.fe_solution(**tpb.REFERENCE_MESH)
    h, delta = 0.5, 2.5
    scene = tpb.pd_scene(h, delta)
    u = fe.at(scene.particles.x)
    work = VirtualWork(scene, beam_fields(delta)[:1] + vf.interior_bumps(
        (0, 0), (tpb.LENGTH, tpb.WIDTH), (6, 1), 2 * delta + 1), {"delta": delta})
    res = identify(work, u)
    truth = tpb.params(delta)
    assert rel(res.params["G"], truth["G"]) < 0.005
    assert rel(res.params["K"], truth["K"]) < 0.02


def test_noise_optimal_fields_give_the_least_squares_estimate(beam):
    """Noisy beam data: iterating the closed form with the noise-optimal fields made at the
    current estimate converges to the minimiser of |y - u(K, G)|^2 (the maximum-likelihood
    estimate, found independently by scipy least_squares on forward solves) to 1e-7."""
    import scipy.optimize
    from bayespd.inverse.vfm import noise_optimal_fields

    scene, truth, u = beam
    y = u + 2e-3 * float(u.abs().max()) * torch.randn(u.shape, generator=torch.Generator().manual_seed(4), dtype=u.dtype)
    est = {"K": 2500.0, "G": 2000.0}
    free_dofs = np.asarray(scene.constraints.free_mask).reshape(u.shape)  # the supports are known exactly
    for _ in range(6):  # a fixed-point iteration: ~3 digits per step here
        work = VirtualWork(scene, noise_optimal_fields(scene, {**est, "delta": DELTA}), {"delta": DELTA})
        est = identify(work, y, observed=free_dofs).params
    free = scene.constraints.free(y)

    def misfit(z):
        with torch.no_grad():
            return (scene.constraints.free(scene.solve({"K": np.exp(z[0]), "G": np.exp(z[1]), "delta": DELTA})) - free).numpy()

    ls = scipy.optimize.least_squares(misfit, np.log([truth["K"], truth["G"]]), jac="3-point",
                                      xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert rel(est["K"], np.exp(ls.x[0])) < 1e-7 and rel(est["G"], np.exp(ls.x[1])) < 1e-7
    assert rel(est["K"], truth["K"]) > 1e-4  # the noise moved the estimate: the agreement is not trivial


def test_moduli_sensitivities_match_central_differences(beam):
    """d u/d(K, G) from one factorisation (d u/d a_k = -K^-1 K_k u, chain rule through the PD
    constants) against central differences of forward solves with step 1e-4: the difference
    is the O(step^2) truncation, below 1e-7 of the largest entry."""
    from bayespd.inverse.vfm import moduli_sensitivities

    scene, truth, _ = beam
    J = moduli_sensitivities(scene, truth)
    columns = []
    with torch.no_grad():
        for name in ("K", "G"):
            step = 1e-4 * truth[name]
            up, down = (scene.solve({**truth, name: truth[name] + s * step}) for s in (1, -1))
            columns.append(scene.constraints.free((up - down) / (2 * step)).numpy())
    reference = np.stack(columns, 1)
    assert J.shape == reference.shape
    assert np.abs(J - reference).max() < 1e-7 * np.abs(reference).max()
