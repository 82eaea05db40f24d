"""bayespd.learn.wave_gp: the GP's conditional (stationary, and with the amplitude growing in |k| h)
is dense Gaussian conditioning of the joint law written out entry by entry (to 1e-10), its
off-diagonal field vanishes on the axes, and a, l, eta (and g, p) drawn into synthetic errors are
recovered within 3 of their stated (Laplace) sds, and the outer frame of such errors has z-scores
of rms 1 under the GP fitted to the inner ones."""
import numpy as np
import pytest
import torch

from bayespd.learn.wave_gp import WaveGP, conditional, draw_errors, fit_wave_gp, frame_extrapolation

GP = WaveGP(0.05, 0.6, 0.01)
GROWING = WaveGP(0.02, 0.6, 0.005, 0.02, 1.5)  # A = 2 % at k = 0, 4.1 % at |k| h = 1.5, 6.6 % at 2.2
SIGMA_M = 0.004


def quadrant(n, step=0.31):
    """The k h of the modes 0 <= n1, n2 < n but (0, 0) on a square lattice of spacing ``step``."""
    m = np.array([(i, j) for i in range(n) for j in range(n) if i or j], float)
    return torch.as_tensor(m * step), torch.as_tensor((m[:, 0] > 0) & (m[:, 1] > 0))


def dense(gp, p, q, odd):
    """A(k) A(k') K_e written as a double loop over the points and the four mirror images."""
    out = np.zeros((len(p), len(q)))
    for i, x in enumerate(p):
        for j, y in enumerate(q):
            for s1 in (1, -1):
                for s2 in (1, -1):
                    g = np.array([s1 * y[0], s2 * y[1]])
                    out[i, j] += (s1 * s2 if odd else 1) * np.exp(-((x - g) ** 2).sum() / (2 * gp.length**2))
            out[i, j] *= np.sqrt((gp.amplitude**2 + gp.growth**2 * (x @ x) ** gp.power)
                                 * (gp.amplitude**2 + gp.growth**2 * (y @ y) ** gp.power))
    return out


@pytest.mark.parametrize("gp", [GP, GROWING])
def test_conditional_is_dense_conditioning(gp):
    kh, off = quadrant(5)
    rng = np.random.default_rng(0)
    Delta = rng.normal(0, 0.05, (len(kh), 2, 2))
    Delta = torch.as_tensor((Delta + Delta.transpose(0, 2, 1)) / 2)
    new = torch.as_tensor(rng.uniform(0, 2.5, (7, 2)))
    got = conditional(gp, kh, Delta, off, SIGMA_M, new)
    x = kh.numpy()
    for e, (w2, odd, held, y) in enumerate(((1.0, False, np.ones(len(x), bool), Delta[:, 0, 0]),
                                             (1.0, False, np.ones(len(x), bool), Delta[:, 1, 1]),
                                             (0.5, True, off.numpy(), Delta[:, 0, 1]))):
        xo, yo = x[held], y.numpy()[held]
        joint = w2 * dense(gp, np.vstack([xo, new]), np.vstack([xo, new]), odd)
        joint[: len(xo), : len(xo)] += w2 * (gp.white**2 + SIGMA_M**2) * np.eye(len(xo))
        A, B, Cn = joint[: len(xo), : len(xo)], joint[len(xo):, : len(xo)], joint[len(xo):, len(xo):]
        mean, cov = B @ np.linalg.solve(A, yo), Cn - B @ np.linalg.solve(A, B.T)
        assert np.abs(got[e][0].numpy() - mean).max() < 1e-10
        assert np.abs(got[e][1].numpy() - cov).max() < 1e-10


def test_off_diagonal_vanishes_on_the_axes_and_spread_grows_away_from_data():
    kh, off = quadrant(4)
    Delta = torch.zeros(len(kh), 2, 2, dtype=torch.float64)
    new = torch.tensor([[1.5, 0.0], [0.0, 2.0], [0.31, 0.31], [3.0, 3.0]], dtype=torch.float64)
    draws = torch.stack([draw_errors(GP, kh, Delta, off, SIGMA_M, new, torch.Generator().manual_seed(i))
                         for i in range(400)])
    assert float(draws[:, :2, 0, 1].abs().max()) <= 4.5 * GP.white / np.sqrt(2)  # white part only
    sd = conditional(GP, kh, Delta, off, SIGMA_M, new)[0][1].diagonal().sqrt()
    assert float(sd[2]) < np.hypot(GP.white, SIGMA_M) and abs(float(sd[3]) - GP.amplitude) < 1e-3 * GP.amplitude  # at a datum / far


def test_hyperparameters_recovered_within_stated_uncertainty():
    kh, off = quadrant(12)
    fit = fit_wave_gp(kh, prior_draw(kh, off, 3), off, 0.0)
    for got, true, sd in zip((fit.amplitude, fit.length, fit.white), GP[:3], fit.log_sd):
        assert abs(np.log(got / true)) < 3 * sd < 1.0


def test_growing_amplitude_recovered_within_stated_uncertainty():
    """a, l, eta, g, p of the growing GP from its own draws on a 12 x 12 lattice of step 0.2 in k h
    (|k| h up to 3.1, the training waves' range 0.3-2.2 and one step beyond) within 3 of their
    stated sds (6 seeds: |z| at most 2.3), and its evidence above the stationary GP's: the
    stationary law misses the growth by about 18 nats here (6 seeds: 6-21)."""
    kh, off = quadrant(12, 0.2)
    Delta = prior_draw(kh, off, 1, GROWING)
    fit = fit_wave_gp(kh, Delta, off, 0.0, growing=True)
    assert len(fit.log_sd) == 5
    for got, true, sd in zip(fit[:5], GROWING[:5], fit.log_sd):
        assert abs(np.log(got / true)) < 3 * sd < 1.0
    assert fit.log_marginal > fit_wave_gp(kh, Delta, off, 0.0).log_marginal + 3.0


def test_a_white_sd_at_its_bound_is_an_answer_with_no_sd():
    """Errors with no white part, fitted with a measurement sd of 0.4 % (above what their residuals
    hold): eta goes to its lower bound, which is reported (sd NaN), the others keep finite sds."""
    kh, off = quadrant(8)
    fit = fit_wave_gp(kh, prior_draw(kh, off, 0, GP._replace(white=0.0)), off, SIGMA_M)
    assert abs(np.log(fit.white) + 12.0) < 1e-5 and np.isnan(fit.log_sd[2])
    assert np.isfinite([fit.log_sd[0], fit.log_sd[1]]).all()


def prior_draw(kh, off, seed, gp=GP):
    """Errors drawn from the GP's law at ``kh`` (conditioned on one datum of a huge error: the prior)."""
    return draw_errors(gp, kh[:1], torch.zeros(1, 2, 2, dtype=torch.float64), off[:1], 1e3, kh,
                       torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("gp, step", [(GP, 0.31), (GROWING, 0.2)])
def test_frame_extrapolation_is_calibrated_on_the_gps_own_errors(gp, step):
    kh, off = quadrant(12, step)
    modes = torch.round(kh / step)
    growing = gp.growth > 0
    rms = [float(frame_extrapolation(modes, kh, prior_draw(kh, off, seed, gp), off, 0.0, growing).pow(2).mean().sqrt())
           for seed in range(3)]
    assert abs(np.mean(rms) - 1.0) < 0.25  # 3 frames of 56 correlated z: sd of the mean rms about 0.09 (6 seeds: 0.78-1.18;
    # growing: 0.96-1.06 for seeds 0-2)
