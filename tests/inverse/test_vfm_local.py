"""``bayespd.inverse.vfm_local``: the weak form on the measured grid and the default VFM on
scikit-fem fields (K and G within 0.5 %); its fields are tested in test_local_fields.py."""
import warnings

import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.inverse.local_fields import local_fields
from bayespd.inverse.vfm import ExactlyDeterminedWarning, identify
from bayespd.inverse.vfm_defaults import estimate
from bayespd.inverse.vfm_local import LocalWork, gradient_operator
from bayespd.inverse.vfm_noise import weighted_identify


def holed_plate(h=1.0):
    """40 x 20 plate, hole of radius 4 at the centre, clamped left, pulled right (bonds at 3 h)."""
    p = bp.grid_2d(40.0, 20.0, h)
    p = p.where(np.linalg.norm(p.x - [20.0, 10.0], axis=1) > 4.0)
    return bp.Scene(bp.LPS(p, bp.find_bonds(p, 3 * h), plane="stress"), [bp.Dirichlet.layer(p, "left", 3 * h)],
                    [bp.Load(p.layer("right", h), (200.0, 0.0))])


def gradient(p, u):
    return (gradient_operator(p) @ u.reshape(-1)).reshape(p.n, p.dim, p.dim)


def test_gradient_is_exact_for_quadratics_on_a_rectangle_and_linears_around_a_hole():
    """Central and second-order one-sided differences are exact for quadratic fields; at the
    hole's staircase some particles have one neighbour along an axis (first order): exact for
    linear fields."""
    p = bp.grid_2d(12.0, 7.0, 0.5)
    x, y = p.x.T
    u = np.stack([x**2 - 3 * x * y + 0.5 * y**2, 2 * x * y - y**2 + x], 1)
    exact = np.stack([np.stack([2 * x - 3 * y, -3 * x + y], 1), np.stack([2 * y + 1, 2 * x - 2 * y], 1)], 1)
    assert np.abs(gradient(p, u) - exact).max() < 1e-10
    q = holed_plate().particles
    A = np.array([[1e-3, -2e-4], [5e-4, 3e-3]])
    assert np.abs(gradient(q, q.x @ A.T) - A).max() < 1e-14


@pytest.fixture(scope="module")
def fe_plate_solution():
    """The scikit-fem Q2 plate with a hole (bayespd.reference.plate_with_hole, h_FE = 0.25 mm),
    nu = 0.37, and the truth."""
    from bayespd.reference import plate_with_hole as ph
    E, nu = 4000.0, 0.37
    K, G = map(float, bp.moduli_from_young(E, nu))
    return ph.fe_solution(0.25, young=E, nu=nu), {"K": K, "G": G}


@pytest.fixture(scope="module")
def fe_plate(fe_plate_solution):
    """The FE plate read on a 0.5 mm grid."""
    from bayespd.reference import plate_with_hole as ph
    scene = ph.pd_scene(0.5, 1.5)
    fe, truth = fe_plate_solution
    return scene, fe.at(scene.particles.x), truth


def test_fe_plate_with_a_hole_within_half_a_percent(fe_plate):
    """The default (local work, harmonic load field + hats) on the FE field: K, G within 0.5 %
    (the issue's target). Measured 0.1 % (K) and 0.01 % (G) at nu = 0.15-0.45 on this grid; the
    weak form's error is the differences' O(h^2) and the staircase kept off by the margin,
    while the PD work with truncated families gave 3.5-5 % on this field."""
    scene, u, truth = fe_plate
    with warnings.catch_warnings():
        warnings.simplefilter("error", ExactlyDeterminedWarning)
        res = estimate(scene, u)
    assert res.extra["work"] == "local" and res.extra["m"] is None and res.extra["fields"] > 10
    for k in ("K", "G"):
        assert abs(res.params[k] / truth[k] - 1) < 5e-3


def test_a_coarse_grid_falls_back_to_smaller_fields_with_a_warning(fe_plate_solution):
    """On a 1 mm grid every default hat (margin 4 h, 8 h apart) meets the hole, the clamp or the
    load: the defaults fall back to margin 3 h, hats 3 h apart (25 fields), warn, and keep K, G
    within 0.5 % (measured 0.03-0.11 % at nu 0.15-0.45); margin= and size= given are used as
    given (and then refused as too few)."""
    from bayespd.inverse.vfm_defaults import FallbackFieldsWarning
    from bayespd.reference import plate_with_hole as ph
    fe, truth = fe_plate_solution
    scene = ph.pd_scene(1.0, 3.0)
    u = fe.at(scene.particles.x)
    with pytest.warns(FallbackFieldsWarning, match="margin 3 h and hats 3 h apart"):
        res = estimate(scene, u)
    assert res.extra["fields"] == 25
    for k in ("K", "G"):
        assert abs(res.params[k] / truth[k] - 1) < 5e-3
    with pytest.raises(ValueError, match="exactly determined"):
        estimate(scene, u, margin=4.0, size=8.0)


def _noisy_estimates(fe_plate, noise: float, draws: int, se_keys) -> np.ndarray:
    """(draws, 2 + 2 len(se_keys)): the relative errors of K, G from the FE plate's field plus noise
    ``noise`` x max |u| (seeded), then each draw's reported ``se_keys`` of K, G."""
    scene, u, truth = fe_plate
    sigma = noise * np.abs(u).max()
    work = LocalWork(scene, local_fields(scene), {"delta": 1.5})
    rng = np.random.default_rng(11)
    rows = []
    for _ in range(draws):
        res = weighted_identify(work, u + sigma * rng.standard_normal(u.shape), sigma, max_se=None)
        rows.append([res.params[k] / truth[k] - 1 for k in ("K", "G")] + [res.extra[s][k] for s in se_keys
                                                                         for k in ("K", "G")])
    return np.array(rows)


def test_noisy_estimate_standard_error_matches_monte_carlo(fe_plate):
    """Noise 0.1 % of max |u| (se of K ~1 %, where the map a -> K is near linear; 1 % noise: the
    slow test below): the errors of 200 draws have the sd that ``weighted_identify`` reports within 4 / sqrt(400) = 20 % (the
    sd of a sample sd, 4 se), their mean is within 4 se / sqrt(200) + the noise-free bias
    (0.2 %), and no draw fails."""
    rows = _noisy_estimates(fe_plate, 1e-3, 200, ("se",))
    se = np.median(rows[:, 2:], axis=0)
    assert np.all(np.abs(rows[:, :2].std(0) / se - 1) < 0.2)
    assert np.all(np.abs(rows[:, :2].mean(0)) < 4 * se / np.sqrt(200) + 2e-3)


@pytest.mark.slow
@pytest.mark.parametrize("nu", [0.15, 0.3, 0.45])
def test_fe_beam_within_half_a_percent(nu):
    """scikit-fem Q2 three-point-bending beam (h_FE = 0.5 mm) on a 1 mm grid: K, G within 0.5 %
    (measured 0.18-0.25 %, 0.01-0.18 % at h = 0.5 mm: the discretisation error of the weak form)."""
    from bayespd.reference import three_point_bending as tpb
    scene = tpb.pd_scene(1.0, 3.0)
    res = estimate(scene, torch.as_tensor(tpb.fe_solution(**tpb.REFERENCE_MESH, nu=nu).at(scene.particles.x)))
    truth = tpb.params(1.0, nu)
    for k in ("K", "G"):
        assert abs(res.params[k] / truth[k] - 1) < 5e-3


def test_scattered_particles_are_refused_naming_the_pd_work():
    x = np.random.default_rng(0).uniform(0, 10, (50, 2))
    with pytest.raises(ValueError, match="regular grid.*work='pd'"):
        gradient_operator(bp.from_points(x, np.ones(50), h=1.0))


def test_a_gap_in_the_data_is_avoided_by_the_default_fields(fe_plate):
    """A DIC-like gap (no data in a 2 mm disc on the ligament right of the hole): the default
    fields keep off it (no field needs the missing displacements) and K, G stay within 0.5 %."""
    scene, u, truth = fe_plate
    y = u.copy()
    y[np.linalg.norm(scene.particles.x - [31.0, 6.0], axis=1) < 2.0] = np.nan
    res = estimate(scene, y)
    for k in ("K", "G"):
        assert abs(res.params[k] / truth[k] - 1) < 5e-3


@pytest.mark.slow
def test_standard_error_at_one_percent_noise_matches_monte_carlo(fe_plate):
    """Noise 1 % of max |u| at nu = 0.37: se K ~19 %, where the map a -> K (a ratio) is far from
    linear and K's distribution is skewed (kurtosis ~5.3, measured). The sd of 1000 draws' K
    errors then has a relative sd sqrt((kurtosis - 1) / 4000) = 3.3 %; the bootstrap se
    (median over the draws) must match it within 4 x 3.3 % = 13 % (measured: 4 % low), which the
    linearised se, 16 % low, fails (so the test can tell them apart). G is near linear: within
    the same 13 %."""
    rows = _noisy_estimates(fe_plate, 1e-2, 1000, ("se", "se_linear"))
    sd, se, linear = rows[:, :2].std(0), np.median(rows[:, 2:4], axis=0), np.median(rows[:, 4:], axis=0)
    assert np.all(np.abs(se / sd - 1) < 0.13)
    assert linear[0] / sd[0] - 1 < -0.13
