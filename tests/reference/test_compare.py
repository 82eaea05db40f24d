"""bayespd/reference/compare.py: relative L2 errors, observed orders, PD against FE."""
import numpy as np
import pytest
import torch

pytest.importorskip("skfem")

from bayespd.reference import observed_order, pd_versus_fe, relative_l2, three_point_bending as beam  # noqa: E402


def test_relative_l2_is_the_frobenius_ratio():
    """||u - r||_F / ||r||_F over points and components: 0 for u = r, 1 for u = 0 or u = 2r,
    eps for u = (1 + eps) r, and a hand-computed 3-4-5 case."""
    r = np.random.default_rng(0).standard_normal((7, 2))
    assert relative_l2(r, r) == 0.0
    assert relative_l2(np.zeros_like(r), r) == pytest.approx(1.0, rel=1e-15)
    assert relative_l2(2 * r, r) == pytest.approx(1.0, rel=1e-15)
    assert relative_l2(1.001 * r, r) == pytest.approx(1e-3, rel=1e-12)
    assert relative_l2(np.array([[3.0, 4.0]]), np.array([[0.0, 5.0]])) == pytest.approx(np.sqrt(10) / 5, rel=1e-15)


@pytest.mark.parametrize("p", [1.0, 2.0, 0.5])
def test_observed_order_of_a_power_law(p):
    """e = C x^p: the least-squares slope on log-log axes is p exactly (1e-12); a noisy
    e = C x^p exp(n), |n| <= 0.01, over a decade still gives p within 0.02 / log(10) per
    end: 0.02."""
    x = np.array([0.25, 0.5, 1.0, 2.0, 2.5])
    assert observed_order(x, 3.0 * x**p) == pytest.approx(p, abs=1e-12)
    noise = np.random.default_rng(1).uniform(-0.01, 0.01, len(x))
    assert observed_order(x, 3.0 * x**p * np.exp(noise)) == pytest.approx(p, abs=0.02)


def test_pd_versus_fe_compares_the_scene_at_the_points_away_from_patches():
    """Beam at h = 2, m = 3 against a Q1 peer on a 2 mm mesh (0.05 s): delta = m h, the
    particles compared are exactly those farther than the margin from every patch, and the
    error is relative_l2 of the PD solution (solved here independently) against the peer at
    them, to rounding; the timings add up."""
    fe = beam.fe_solution(h=2.0, order=1, grading=0)
    row = pd_versus_fe(beam, 2.0, 3, {"q1": fe}, 4.0)
    scene = beam.pd_scene(2.0, 6.0)
    x = scene.particles.x
    keep = beam.away_mask(x, 4.0)
    with torch.no_grad():
        u = scene.solve(beam.params(6.0)).numpy()
    assert row["delta"] == 6.0 and row["n_particles"] == 64 * 16 and row["n_compared"] == keep.sum() > 0
    assert row["errors"]["q1"] == pytest.approx(relative_l2(u[keep], fe.at(x[keep])), rel=1e-12)
    assert 0 < row["errors"]["q1"] < 1
    assert row["pd_wall_time_s"] == pytest.approx(row["pd_build_s"] + row["pd_solve_s"], rel=1e-12)
