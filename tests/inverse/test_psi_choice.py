"""bayespd/inverse/psi_choice.py: the Tikhonov weight psi by the discrepancy principle (the
residual equals the noise level) and by the L-curve corner; sweeps and refused input."""
import numpy as np
import pytest
import torch

from bayespd.inverse.psi_choice import discrepancy, lcurve, lcurve_corner, psi_sweep
from bayespd.inverse.least_squares import tikhonov
from bayespd.scenes.tikhonov_square import DELTA, K0, MU0, square_scene

TRUTH = {"K": K0, "G": MU0}


@pytest.fixture(scope="module")
def square():
    """Turner 2015 §4.1: the 11 x 11 square and its manufactured data."""
    scene = square_scene()
    return scene, scene.observe(scene.solve(dict(TRUTH, delta=DELTA))).detach()


@pytest.fixture(scope="module")
def noisy_square(square):
    scene, y = square
    noise = 0.01 * float(y.abs().max())
    gen = torch.Generator().manual_seed(7)
    return scene, y + noise * torch.randn(y.shape, generator=gen), noise


def test_discrepancy_principle_matches_the_noise_level(noisy_square):
    """The chosen psi leaves a residual rms equal to tau times the noise sd (rtol 1e-3); the
    sweep brackets it. tau = 1.1: this noise draw's own rms is 1.06 sd (242 entries: the
    sample rms scatters by 1/sqrt(2 * 242) = 4.5 %), so tau = 1 has no solution here."""
    scene, y, noise = noisy_square
    ref = {"K": 300.0, "G": 200.0}
    choice = discrepancy(scene, y, ref, noise=noise, tau=1.1, psis=np.logspace(-1, 5, 7),
                         fixed={"delta": DELTA}, sigma=noise, gtol=1e-8)
    assert choice.attained
    assert abs(choice.result.residual_rms / (1.1 * noise) - 1) < 1e-3
    assert choice.residual_rms[0] < 1.1 * noise < choice.residual_rms[-1]
    with pytest.raises(ValueError, match="noise level"):
        discrepancy(scene, y, ref, noise=None, psis=[1.0, 2.0], fixed={"delta": DELTA})


def test_lcurve_corner_of_a_known_curve():
    """(log rho, log eta) = (e^t, e^-t), t = log psi, is the hyperbola b = 1/a: by symmetry its
    curvature peaks at a = b = 1, psi = 1; second-order differences on a 0.25-step grid
    place it to O(0.25^2)."""
    psis = np.exp(np.arange(-3.0, 3.01, 0.25) + 0.1)
    psi, kappa = lcurve_corner(psis, np.exp(np.exp(np.log(psis))), np.exp(np.exp(-np.log(psis))))
    assert abs(np.log(psi)) < 0.03
    assert kappa.max() == pytest.approx(1 / np.sqrt(2), rel=0.05)  # curvature of b = 1/a at (1, 1)


def test_lcurve_on_the_noisy_square(noisy_square):
    """The corner lies where the misfit stops being flat: its residual stays within 10 % of the
    unregularised fit's (the noise floor), while the strongest psi of the sweep misfits more."""
    scene, y, noise = noisy_square
    choice = lcurve(scene, y, {"K": 300.0, "G": 200.0}, psis=np.logspace(-3, 3, 7),
                    fixed={"delta": DELTA}, sigma=noise, gtol=1e-8)
    floor = tikhonov(scene, y, {"K": 300.0, "G": 200.0}, fixed={"delta": DELTA}, sigma=noise).residual_rms
    assert choice.result.residual_rms < 1.1 * floor < choice.residual_rms[-1]


def test_lcurve_corner_of_a_sharp_l():
    """Two straight branches in (log misfit, log penalty) meeting at t = log psi = 0 (a
    flat misfit then a flat penalty, rounded over one step): the curvature peaks at the
    corner's grid point (to the 0.25 spacing), and its sign says the curve turns left."""
    t = np.arange(-3.0, 3.01, 0.25)
    x = np.logaddexp(0.0, 4 * t)   # misfit: flat, then growing
    y = np.logaddexp(0.0, -4 * t)  # penalty: growing, then flat
    psi, kappa = lcurve_corner(np.exp(t), np.exp(x), np.exp(y))
    assert abs(np.log(psi)) <= 0.25 and kappa.max() > 0 and np.argmax(kappa) == np.argmin(np.abs(t))


@pytest.fixture(scope="module")
def small_square():
    """The same square on 6 x 6 particles (h = 200, delta = 600): fast solves."""
    scene = square_scene(h=200.0, delta=600.0)
    return scene, scene.observe(scene.solve(dict(TRUTH, delta=600.0))).detach()


def test_sweep_is_sorted_and_each_result_solves_at_its_psi(small_square):
    """psi_sweep sorts the psis, solves from the largest down (warm starts) and returns the
    results in ascending psi; a stronger psi pulls toward the reference, so the misfit grows
    and the penalty shrinks monotonically (a Tikhonov identity)."""
    scene, y = small_square
    psis, results = psi_sweep(scene, y, {"K": 300.0, "G": 200.0}, [1e2, 1e-2, 1.0], fixed={"delta": 600.0},
                              sigma=1e-3, gtol=1e-10)
    np.testing.assert_array_equal(psis, [1e-2, 1.0, 1e2])
    misfit = [r.misfit_norm for r in results]
    penalty = [r.penalty_norm for r in results]
    assert misfit[0] < misfit[1] < misfit[2] and penalty[0] > penalty[1] > penalty[2]
    with pytest.raises(ValueError, match="at least two finite, positive"):
        psi_sweep(scene, y, {"K": 300.0, "G": 200.0}, [1.0], fixed={"delta": 600.0})
    with pytest.raises(ValueError, match="at least two finite, positive"):
        psi_sweep(scene, y, {"K": 300.0, "G": 200.0}, [0.0, 1.0], fixed={"delta": 600.0})


def test_discrepancy_outside_the_sweep_is_not_attained(small_square):
    """Noise-free data: every residual of a sweep over strong psis exceeds a tiny noise
    level, so the smallest psi is returned with attained = False; a huge noise level no psi
    reaches: the largest, attained = False. The sweep given once is reused (no new solves)."""
    scene, y = small_square
    sweep = psi_sweep(scene, y, {"K": 300.0, "G": 200.0}, [1e3, 1e4], fixed={"delta": 600.0}, sigma=1e-3)
    low = discrepancy(scene, y, {"K": 300.0, "G": 200.0}, noise=1e-12, sweep=sweep, fixed={"delta": 600.0})
    assert low.attained is False and low.psi == 1e3 and low.result is sweep[1][0]
    high = discrepancy(scene, y, {"K": 300.0, "G": 200.0}, noise=1e6, sweep=sweep, fixed={"delta": 600.0})
    assert high.attained is False and high.psi == 1e4 and high.rule == "discrepancy"
    with pytest.raises(ValueError, match="finite and positive"):
        discrepancy(scene, y, {"K": 300.0, "G": 200.0}, noise=-1.0, sweep=sweep)


def test_lcurve_corner_refuses_short_or_non_positive_sweeps():
    with pytest.raises(ValueError, match="at least 5 values"):
        lcurve_corner([1, 2, 3, 4], [1, 2, 3, 4], [4, 3, 2, 1])
    with pytest.raises(ValueError, match="positive and finite"):
        lcurve_corner([1, 2, 3, 4, 5], [1, 2, np.inf, 4, 5], [5, 4, 3, 2, 1])


def test_lcurve_corner_refuses_a_zero_norm_with_its_message():
    """A zero misfit (an exact fit at the weakest psi) is refused with the ValueError that
    says the norms must be positive, not a divide-by-zero warning."""
    with pytest.raises(ValueError, match="positive and finite"):
        lcurve_corner([1, 2, 3, 4, 5], [0, 2, 3, 4, 5], [5, 4, 3, 2, 1])
