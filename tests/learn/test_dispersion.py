"""bayespd.learn.dispersion: the compliance measured from the sinusoidal loads of a PD sheet is its
own symbol's inverse (the relative error Delta vanishes to rounding), and a model-error draw has
the law it states (per-entry variances, chi-square); the common offset's conditional posterior is
Gaussian conditioning of the joint law (to 1e-12) and its 90 % intervals are calibrated; with a
measurement error the training orbits' model errors are dense conditioning too; the power share
and the off-orbit response of sinusoidal loads are exact on a lattice; on the self-mirror
wavevectors the error field's Delta_01 is 0 and elsewhere it is what was drawn; the unheld
response's white draw has its stated sd and the off-orbit response it was measured from."""
import numpy as np
import pytest
import torch
from scipy import stats

from bayespd.learn import graphene, md_loads
from bayespd.learn.coarse_grain import coarse_grain
from bayespd.learn.dispersion import (common_offset_posterior, common_offset_prior, error_field, measured_compliance,
                                      off_orbit_response, orbit_error_posterior, orbit_errors_on_lattice,
                                      mirror_frame, relative_compliance_error, shell_of, shell_power_share, unheld_part, unheld_response,
                                      unheld_response_sd, wave_power_share)
from bayespd.learn.periodic import periodic_grid
from bayespd.learn.kernel import lps_params
from bayespd.linalg.sparse import NotPositiveDefiniteError
from tests.learn.test_kernel import sheet

LAM, MU, D = -1.0, 3.0, [0.5, 2.0, 1.0]


def eq51_forces(s, modes):
    """Eq 5.1's loads cos(k1 x1) cos(k2 x2) e_a at every (n1, n2) of ``modes``, both axes."""
    x = s.material.particles.x
    out = []
    for n1, n2 in modes:
        k = 2 * np.pi * np.array([n1, n2]) / s.box
        for a in (0, 1):
            f = np.zeros_like(x)
            f[:, a] = np.cos(k[0] * x[:, 0]) * np.cos(k[1] * x[:, 1])
            out.append(f)
    return torch.as_tensor(np.array(out))


def pd_sheet():
    s = sheet()
    return s, int(round(np.sqrt(s.n))), lps_params(LAM, MU, D, 2.6 * s.material.particles.h)


def test_a_pd_sheet_measures_its_own_symbol():
    """Delta = L^T C L - I = 0 to rounding when C is measured from the PD solves themselves
    (both mirror modes of an off-axis wave averaged in); the off-diagonal flags mark n1 n2 != 0."""
    s, n, p = pd_sheet()
    modes = [(1, 0), (0, 2), (1, 1), (2, 1), (1, 3)]
    f = eq51_forces(s, modes)
    with torch.no_grad():
        u = s.spectral_solve(p, f)
    found, C, off = measured_compliance(f, u, n)
    assert sorted(map(tuple, found.tolist())) == sorted(modes)
    assert off.tolist() == [bool(a and b) for a, b in found]
    S = s.symbol(p, torch.as_tensor(found * 2 * np.pi / s.box)).detach()
    Delta, _ = relative_compliance_error(S, C)
    assert float(Delta.abs().max()) < 1e-12


def test_a_wave_without_its_second_load_is_refused():
    s, n, _ = pd_sheet()
    f = eq51_forces(s, [(1, 1)])[:1]
    with pytest.raises(ValueError, match="lack their x or y load"):
        measured_compliance(f, f, n)


def test_an_indefinite_symbol_is_a_refused_point():
    with pytest.raises(NotPositiveDefiniteError, match="solvability"):
        relative_compliance_error(-torch.eye(2, dtype=torch.float64)[None], torch.eye(2, dtype=torch.float64)[None])


def test_shells_by_wavenumber():
    assert shell_of(np.array([[0.1, 0.0], [0.3, 0.4]]), 1.0, (0.2, 0.4)).tolist() == [0, 2]
    with pytest.raises(ValueError, match="increasing"):
        shell_of(np.zeros((1, 2)), 1.0, (0.4, 0.2))


@pytest.mark.parametrize("measurement", [0.0, 0.02])
def test_the_error_field_has_the_stated_law(measurement):
    """Delta = L^T X L read back from a draw at the wave (1, 2) (X's columns: e_hat / f_hat of its
    x and y loads there), with the common offset drawn from its prior and a fresh measurement error
    of sd sigma_m, has entries N(0, s^2 + tau^2 + sigma_m^2) on the diagonal and half that off it: over 400 draws each variance's chi-square statistic lies in its two-sided 99 % range
    (a 1 % false rejection each; a variance off by 25 % is rejected with power above 0.99: the
    statistic's mean moves by 100 against its sd of 28)."""
    s, n, p = pd_sheet()
    k_all = s.wavevectors
    S = s.symbol(p, k_all).detach()
    f = eq51_forces(s, [(1, 2)])
    f_hat = torch.fft.fft2(f.reshape(2, n, n, 2), dim=(1, 2))[:, 1, 2]
    L = torch.linalg.cholesky(S[1 * n + 2 - 1])  # wavevectors omit k = 0
    sd, tau, draws = 0.03, 0.02, 400
    generator = torch.Generator().manual_seed(1)
    Delta = []
    for _ in range(draws):
        e = error_field(S, f, torch.full((len(k_all),), sd), common_offset_prior(tau).sample(generator), n, generator,
                        measurement=measurement)
        e_hat = torch.fft.fft2(e.reshape(2, n, n, 2), dim=(1, 2))[:, 1, 2]
        X = torch.stack([(e_hat[a] / f_hat[a, a]).real for a in (0, 1)], -1)
        Delta.append(L.T @ X @ L)
    Delta = torch.stack(Delta)
    var = sd**2 + tau**2 + measurement**2
    for values, v in ((Delta[:, 0, 0], var), (Delta[:, 1, 1], var), (Delta[:, 0, 1], var / 2)):
        chi2 = float((values**2).sum()) / v
        assert stats.chi2.ppf(0.005, draws) < chi2 < stats.chi2.ppf(0.995, draws)


ENTRIES = ((0, 0), (1, 1), (0, 1))
SCALE = np.array([1.0, 1.0, np.sqrt(0.5)])  # CompliancePerOrbit's entry scales (diagonal, off-diagonal)


def offset_data(rng, orbits, tau):
    """A known offset c from the prior, per-orbit sds s, off-diagonal flags and Delta = c + eps drawn
    from models/md_dispersion.py's law (eps_oe ~ N(0, w_e^2 s_o^2))."""
    s = rng.uniform(0.02, 0.06, orbits)
    off = rng.random(orbits) < 0.6
    c = tau * SCALE * rng.standard_normal(3)
    Delta = np.zeros((orbits, 2, 2))
    for (i, j), c_e, w in zip(ENTRIES, c, SCALE):
        Delta[:, i, j] = c_e + w * s * rng.standard_normal(orbits)
        Delta[:, j, i] = Delta[:, i, j]
    Delta[~off, 0, 1] = Delta[~off, 1, 0] = rng.standard_normal((~off).sum())  # not data: must be ignored
    return torch.as_tensor(Delta), torch.as_tensor(s), torch.as_tensor(off), c


def test_the_common_offset_posterior_is_gaussian_conditioning():
    """Mean and variance of (c_00, c_11, c_01) given the held entries of Delta equal the dense
    conditioning of their joint Gaussian (numpy: cov_cy cov_yy^-1 y, cov_cc - cov_cy cov_yy^-1 cov_yc)
    to 1e-12 relative; with no off-diagonal orbit the 01 entry keeps its prior."""
    rng, tau = np.random.default_rng(3), 0.02
    for orbits in (15, 4):
        Delta, s, off, _ = offset_data(rng, orbits, tau)
        if orbits == 4:
            off[:] = False
        rows, y, noise = [], [], []
        for e, (i, j) in enumerate(ENTRIES):
            for o in range(orbits):
                if e < 2 or off[o]:
                    rows.append(e)
                    y.append(float(Delta[o, i, j]))
                    noise.append((SCALE[e] * float(s[o])) ** 2)
        A = np.eye(3)[rows]  # y = A c + eps
        cov_cc = np.diag((SCALE * tau) ** 2)
        cov_yy = A @ cov_cc @ A.T + np.diag(noise)
        cov_cy = cov_cc @ A.T
        mean = cov_cy @ np.linalg.solve(cov_yy, np.array(y))
        var = np.diag(cov_cc - cov_cy @ np.linalg.solve(cov_yy, cov_cy.T))
        post = common_offset_posterior(Delta, s, tau, off)
        got_mean = np.array([float(post.mean[i, j]) for i, j in ENTRIES])
        got_var = np.array([float(post.sd[i, j]) ** 2 for i, j in ENTRIES])
        assert np.abs(got_mean - mean).max() < 1e-12 * tau
        assert np.abs(got_var / var - 1).max() < 1e-12
        assert post.mean[0, 1] == post.mean[1, 0] and post.sd[0, 1] == post.sd[1, 0]
    assert float(post.mean[0, 1]) == 0.0 and abs(float(post.sd[0, 1]) - tau * SCALE[2]) < 1e-15


def test_the_common_offset_posterior_intervals_are_calibrated():
    """Offsets drawn from the prior, data from the model: the 90 % posterior interval m_e +- 1.645 sd_e
    holds c_e in 3 x 2,000 independent cases at rate 0.9 within 3.29 binomial sd (0.0127; a 0.1 %
    false rejection). An interval 15 % too narrow or too wide (rate 0.838 or 0.941) moves it by
    >= 10 sd, and one that ignores the data beyond the prior's mean (m = 0, the posterior sd) by
    more: power > 0.999. The sampler's draws have the law's mean and sd (z-tests, 4 sd)."""
    rng, tau, replicates = np.random.default_rng(7), 0.02, 2000
    inside = []
    for _ in range(replicates):
        Delta, s, off, c = offset_data(rng, 12, tau)
        post = common_offset_posterior(Delta, s, tau, off)
        for (i, j), c_e in zip(ENTRIES, c):
            inside.append(abs(c_e - float(post.mean[i, j])) <= stats.norm.ppf(0.95) * float(post.sd[i, j]))
    rate, sd = np.mean(inside), np.sqrt(0.9 * 0.1 / len(inside))
    assert abs(rate - 0.9) < stats.norm.ppf(1 - 0.0005) * sd
    generator, draws = torch.Generator().manual_seed(0), 4000
    samples = torch.stack([post.sample(generator) for _ in range(draws)])
    for i, j in ENTRIES:
        z = (samples[:, i, j] - post.mean[i, j]) / post.sd[i, j]
        assert abs(float(z.mean())) < 4 / np.sqrt(draws)
        assert abs(float(z.var()) - 1) < 4 * np.sqrt(2 / draws)
    assert torch.equal(samples[:, 0, 1], samples[:, 1, 0])


def test_orbit_errors_given_measurement_error_are_gaussian_conditioning():
    """Delta_oe = c_e + eps_oe + m_oe (m ~ N(0, w_e^2 sigma^2)): the model errors t_oe = c_e + eps_oe given
    every held Delta, drawn as c from common_offset_posterior (total sds sqrt(s^2 + sigma^2)) and then
    t | c from orbit_error_posterior, have the mean and covariance of numpy's dense conditioning of the
    joint Gaussian of (t, Delta) to 1e-12, per entry (t_o affine in c: mean(c) = a_o c + b_o, so
    E t = a m_c + b, Cov(t_o, t_o') = a_o a_o' v_c + [o = o'] sd_o^2); sigma = 0 pins Delta itself."""
    rng, tau, sigma = np.random.default_rng(11), 0.02, 0.012
    Delta, s, off, _ = offset_data(rng, 9, tau)
    post = common_offset_posterior(Delta, (s**2 + sigma**2).sqrt(), tau, off)
    zero, one = torch.zeros(2, 2, dtype=Delta.dtype), torch.ones(2, 2, dtype=Delta.dtype)
    at0, at1 = orbit_error_posterior(Delta, s, sigma, zero), orbit_error_posterior(Delta, s, sigma, one)
    for e, (i, j) in enumerate(ENTRIES):
        held = np.ones(len(s), bool) if e < 2 else off.numpy()
        y, sd = Delta[held, i, j].numpy(), s.numpy()[held]
        T = (SCALE[e] * tau) ** 2
        cov_tt = T + np.diag((SCALE[e] * sd) ** 2)
        cov_yy = cov_tt + np.eye(len(y)) * (SCALE[e] * sigma) ** 2
        mean = cov_tt @ np.linalg.solve(cov_yy, y)  # cov_ty = cov_tt
        cov = cov_tt - cov_tt @ np.linalg.solve(cov_yy, cov_tt)
        a = (at1.mean[held, i, j] - at0.mean[held, i, j]).numpy()
        m_c, v_c = float(post.mean[i, j]), float(post.sd[i, j]) ** 2
        got_mean = a * m_c + at0.mean[held, i, j].numpy()
        got_cov = np.outer(a, a) * v_c + np.diag(at0.sd[held, i, j].numpy() ** 2)
        assert np.abs(got_mean - mean).max() < 1e-12 * tau
        assert np.abs(got_cov - cov).max() < 1e-12 * np.abs(cov).max()
    exact = orbit_error_posterior(Delta, s, 0.0, post.mean)
    assert float((exact.mean - Delta).abs().max()) < 1e-15 and float(exact.sd.abs().max()) == 0.0
    with pytest.raises(ValueError, match="non-negative"):
        orbit_error_posterior(Delta, s, -0.01, zero)


def test_power_share_and_off_orbit_response_of_lattice_waves():
    """On the 10 x 10 sheet's nodes eq 5.1's loads are exact lattice waves: each puts its whole power
    on its own orbit and none on another (DFT orthogonality, to 1e-12), and the PD response holds no
    off-orbit part (1e-12) until a second harmonic of known relative size 0.01 is added (read back to
    1e-12). On a graphene sheet coarse-grained onto a 12 x 12 grid (atoms, plain cone), the unseen
    waves (max(n1, n2) = 2, 3 beyond training modes n <= 1) put under 1e-3 of their power on the
    training orbits, the training waves over 0.999 (measured 1.3e-4 and 0.99995: the cone's lattice sums
    leak the rest)."""
    s, n, p = pd_sheet()
    f = eq51_forces(s, [(1, 0), (2, 1), (3, 3)])
    share = wave_power_share(f, [(2, 1)], n)
    assert np.abs(share.numpy() - [0, 0, 1, 1, 0, 0]).max() < 1e-12
    with torch.no_grad():
        u = s.spectral_solve(p, f)
    assert float(off_orbit_response(f, u, n).max()) < 1e-12
    x = s.material.particles.x
    k2 = 2 * 2 * np.pi * np.array([1, 0]) / s.box  # the second harmonic of the (1, 0) loads
    harmonic = torch.as_tensor(np.cos(k2[0] * x[:, 0]))[:, None] * torch.tensor([1.0, 0.0], dtype=u.dtype)
    y = u[0] + 0.01 * u[0].norm() / harmonic.norm() * harmonic
    assert abs(float(off_orbit_response(f[:1], y[None], n)[0]) - 0.01 / np.sqrt(1 + 0.01**2)) < 1e-12
    atoms, box = graphene.sheet(12, 7, 1.42)
    nodes = periodic_grid(box, 12)
    loads = [md_loads.sinusoidal(atoms, box, a, b, c, 0.002) for a, b, c in md_loads.sinusoidal_cases(1)]
    unseen = [md_loads.sinusoidal(atoms, box, a, b, c, 0.002) for a, b, c in md_loads.unseen_cases(1)]
    forces = np.stack(loads + unseen)
    cg = coarse_grain(nodes.x, atoms, np.ones(len(atoms)), forces, forces, 2 * nodes.h, float(nodes.volume[0]),
                      weno=False, box=box)
    share = wave_power_share(torch.as_tensor(cg.b), [(0, 1), (1, 0), (1, 1)], 12).numpy()
    assert share[: len(loads)].min() > 0.999 and share[len(loads):].max() < 1e-3


def test_known_orbit_errors_are_what_the_loads_then_measure():
    """An error field with the orbits' errors pinned (orbit_errors_on_lattice: the mirror pair's
    M Delta M) added to the PD response of eq 5.1's loads on those orbits measures back Delta_o
    (diagonal; off it where n1 n2 != 0, else 0) to 1e-12, whatever the other wavevectors draw;
    an axis orbit folds its coinciding wavevectors."""
    s, n, p = pd_sheet()
    modes = np.array([(1, 0), (0, 2), (1, 1), (2, 3), (4, 1)])
    rng = np.random.default_rng(5)
    Delta = torch.as_tensor(rng.normal(0, 0.05, (len(modes), 2, 2)))
    Delta = (Delta + Delta.transpose(-1, -2)) / 2
    index, values = orbit_errors_on_lattice(modes, Delta, n)
    assert len(index) == 2 + 2 + 4 + 4 + 4 and len(set(index.tolist())) == len(index)
    f = eq51_forces(s, modes)
    with torch.no_grad():
        u = s.spectral_solve(p, f)
        S = s.symbol(p, s.wavevectors)
    generator = torch.Generator().manual_seed(0)
    e = error_field(S, f, torch.full((n * n - 1,), 0.05), common_offset_prior(0.03).sample(generator), n, generator,
                    known=(index, values))
    found, C, off = measured_compliance(f, u + e, n)
    assert found.tolist() == sorted(modes.tolist())
    order = [modes.tolist().index(m) for m in found.tolist()]
    got, _ = relative_compliance_error(s.symbol(p, torch.as_tensor(found * 2 * np.pi / s.box)).detach(), C)
    want = Delta[order].clone()
    want[~off, 0, 1] = want[~off, 1, 0] = 0.0
    assert float((got - want).abs().max()) < 1e-12


def test_mirror_frame_maps_each_wavevector_to_its_orbit():
    """Each wavevector's representative is the one of its orbit {(+-n1, +-n2)} with 0 <= n1, n2 <= n / 2,
    and its 01 sign is that of M^a Delta M^a (a: the mirrors that carry the representative there):
    0 exactly on the wavevectors some mirror maps onto themselves (mod n), 35 of 99 on a 10 x 10
    lattice, the axes alone (20 of 120) on an 11 x 11 one."""
    for n, count in ((10, 35), (11, 20)):
        rep, sign = mirror_frame(n)
        for flat, (r, sg) in enumerate(zip(rep.tolist(), sign.tolist()), 1):
            i, j = divmod(flat, n)
            images = {(s1 * (r // n) % n, s2 * (r % n) % n): s1 * s2 for s1 in (1, -1) for s2 in (1, -1)}
            assert (i, j) in images and 2 * (r // n) <= n and 2 * (r % n) <= n
            fixed = i == -i % n or j == -j % n
            assert sg == (0 if fixed else images[(i, j)])
        assert int((sign == 0).sum()) == count


def test_the_error_field_is_diagonal_on_the_self_mirror_waves_and_unchanged_elsewhere():
    """With s = 0 the drawn Delta is the offset c alone, in each orbit's frame: eq 5.1's loads on the
    PD response plus the field measure back c at the off-axis waves (all three entries, to 1e-12:
    the mirror pair carries M c M, which measured_compliance maps back) and diag(c) on the axis
    waves, with Delta_01 below 1e-14 against c_01 = 0.02 (no mirror pair to average there: the
    frame's sign zeroes it); read directly at the Nyquist line (5, 2), the same."""
    s, n, p = pd_sheet()
    modes = np.array([(2, 0), (0, 3), (1, 1), (2, 3), (4, 1)])
    f = eq51_forces(s, modes)
    with torch.no_grad():
        u = s.spectral_solve(p, f)
        S = s.symbol(p, s.wavevectors)
    c = torch.tensor([[0.03, 0.02], [0.02, -0.01]], dtype=torch.float64)
    zero = torch.zeros(n * n - 1, dtype=torch.float64)
    e = error_field(S, f, zero, c, n, torch.Generator().manual_seed(0))
    found, C, off = measured_compliance(f, u + e, n)
    got, _ = relative_compliance_error(s.symbol(p, torch.as_tensor(found * 2 * np.pi / s.box)).detach(), C)
    assert found.tolist() == [[0, 3], [1, 1], [2, 0], [2, 3], [4, 1]] and (~off).tolist() == [True, False, True, False, False]
    assert float((got[off] - c).abs().max()) < 1e-12
    assert float((got[~off].diagonal(dim1=-2, dim2=-1) - c.diagonal()).abs().max()) < 1e-12
    assert float(got[~off, 0, 1].abs().max()) < 1e-14
    f5 = eq51_forces(s, [(5, 2)])
    e5 = error_field(S, f5, zero, c, n, torch.Generator().manual_seed(0))
    e_hat = torch.fft.fft2(e5.reshape(2, n, n, 2), dim=(1, 2))[:, 5, 2]
    f_hat = torch.fft.fft2(f5.reshape(2, n, n, 2), dim=(1, 2))[:, 5, 2]
    L = torch.linalg.cholesky(S[5 * n + 2 - 1])
    nyquist = L.T @ torch.stack([(e_hat[a] / f_hat[a, a]).real for a in (0, 1)], -1) @ L
    assert abs(float(nyquist[0, 1])) < 1e-14 and float((nyquist.diagonal() - c.diagonal()).abs().max()) < 1e-12


def test_unheld_response_has_its_sd_and_reproduces_the_off_orbit_response():
    """Synthetic records: the PD response of eq 5.1's loads plus a known off-orbit part (the second
    harmonic, relative sizes 0.3, 0.6, 0.9, 1.2 %): off_orbit_response reads each back (1e-12) and
    their rms is the unheld response's sd. Its white draw on 40 PD records ((1, 0) along x and y;
    200 values each) has the stated variance (chi-square over the 8000 values in its two-sided 99 %
    range; a variance off by 5 % moves the statistic by 400 against its sd of 126) and puts the
    share 1 - 2 / 100 of its power off the orbit (an axis orbit holds 2 of the 100 wavevectors): the
    records' rms off-orbit response is sd sqrt(0.98) within 3 % (rms over 40 records of about 200
    values: about 0.8 % relative sd)."""
    s, n, p = pd_sheet()
    f = eq51_forces(s, [(1, 0), (2, 1)])
    with torch.no_grad():
        u = s.spectral_solve(p, f)
    sizes = np.array([0.003, 0.006, 0.009, 0.012])
    measured = off_orbit_response(f, with_harmonic(s, u, [(1, 0), (1, 0), (2, 1), (2, 1)], sizes), n)
    assert np.abs(measured.numpy() - sizes).max() < 1e-12
    sd = float(measured.pow(2).mean().sqrt())
    records = u[:2].repeat(20, 1, 1)
    drawn = unheld_response(records, sd, torch.Generator().manual_seed(3))
    scale = records.pow(2).mean((1, 2), keepdim=True).sqrt()
    chi2 = float(((drawn - records) / (sd * scale)).pow(2).sum())
    assert stats.chi2.ppf(0.005, records.numel()) < chi2 < stats.chi2.ppf(0.995, records.numel())
    response = off_orbit_response(f[:2].repeat(20, 1, 1), drawn, n)
    assert abs(float(response.pow(2).mean().sqrt()) / sd - np.sqrt(1 - 2 / n**2)) < 0.03
    with pytest.raises(ValueError, match="non-negative"):
        unheld_response(records, -0.01, torch.Generator())


def with_harmonic(s, u, modes, sizes):
    """Responses ``u`` of eq 5.1's loads at ``modes`` plus their second harmonic (both components),
    of relative size ``sizes`` (its norm over the record's)."""
    x = s.material.particles.x
    out = []
    for m, ((n1, n2), size) in enumerate(zip(modes, sizes)):
        k = 2 * 2 * np.pi * np.array([n1, n2]) / s.box
        harmonic = torch.as_tensor(np.cos(x @ k))[:, None] * torch.tensor([1.0, 1.0], dtype=u.dtype)
        r = size / np.sqrt(1 - size**2)  # off-orbit norm / total norm = size
        out.append(u[m] + r * u[m].norm() / harmonic.norm() * harmonic)
    return torch.stack(out)


def test_the_unheld_part_is_what_no_real_compliance_holds():
    """PD responses of eq 5.1's loads plus a second harmonic (off the orbit) and a phase-shifted copy
    of the wave (sin for cos along the load: on the orbit, an imaginary compliance): unheld_part
    is the norm of exactly what was added over the record's (1e-12), and 0 (1e-12) for the PD
    responses alone, while off_orbit_response sees the harmonic only."""
    s, n, p = pd_sheet()
    modes = [(1, 0), (2, 1)]
    f = eq51_forces(s, modes)
    with torch.no_grad():
        u = s.spectral_solve(p, f)
    assert float(unheld_part(f, u, n).abs().max()) < 1e-12
    x = s.material.particles.x
    y = with_harmonic(s, u, [m for m in modes for _ in (0, 1)], [0.004, 0.002, 0.006, 0.003])
    for m, (n1, n2) in enumerate(m for m in modes for _ in (0, 1)):
        k = 2 * np.pi * np.array([n1, n2]) / s.box
        shifted = torch.zeros_like(u[m])
        shifted[:, m % 2] = torch.as_tensor(np.sin(k[0] * x[:, 0]) * np.cos(k[1] * x[:, 1]))
        y[m] += 0.005 * (m + 1) * u[m].norm() / shifted.norm() * shifted
    added = (y - u).norm(dim=(1, 2)) / y.norm(dim=(1, 2))
    assert float((unheld_part(f, y, n) - added).abs().max()) < 1e-12
    assert bool((added - off_orbit_response(f, y, n) > 0.002).all())  # the phase part: 0.5-2 %


def test_unheld_response_sd_per_shell_of_the_training_records():
    """Training loads on two shells of |k| h with known off-orbit sizes (1e-3 .. 6e-3): a new wave
    in a shell gets that shell's rms (1e-12), a load with its power split 1 : 3 between the shells
    the power-weighted mean square, and a load on a shell no training load reaches is refused."""
    s, n, p = pd_sheet()
    h = s.material.particles.h
    edges = (1.0, 1.6)
    shell = shell_of(s.wavevectors.numpy(), h, edges)
    modes = [(1, 0), (1, 1), (2, 1), (2, 2)]  # |k| h 0.63, 0.89 (shell 0); 1.40, 1.78 (shells 1, 2)
    assert shell_of(2 * np.pi * np.array(modes) / s.box, h, edges).tolist() == [0, 0, 1, 2]
    f = eq51_forces(s, modes)
    with torch.no_grad():
        u = s.spectral_solve(p, f)
    sizes = np.array([1, 2, 3, 4, 5, 6, 2, 3]) * 1e-3
    y = with_harmonic(s, u, [m for m in modes for _ in (0, 1)], sizes)
    shell0, shell1 = np.sqrt(np.mean(sizes[:4] ** 2)), np.sqrt(np.mean(sizes[4:6] ** 2))
    new = eq51_forces(s, [(0, 1), (1, 2)])  # shells 0 and 1
    mixed = new[0] + np.sqrt(6) * new[2]  # power 1 : 3 (a cos cos wave has half the power of a cos)
    loads = torch.cat([new, mixed[None]])
    got = unheld_response_sd(f, y, loads, shell, n, 3).numpy()
    want = [shell0, shell0, shell1, shell1, np.sqrt((shell0**2 + 3 * shell1**2) / 4)]
    assert np.abs(got - want).max() < 1e-12
    assert np.abs(shell_power_share(loads, shell, n, 3)[-1].numpy() - [0.25, 0.75, 0]).max() < 1e-12
    with pytest.raises(ValueError, match="no training load reaches the shells \\[2\\]"):
        unheld_response_sd(f[:6], y[:6], eq51_forces(s, [(2, 2)]), shell, n, 3)


def test_bad_offset_input_is_refused():
    Delta, s, off, _ = offset_data(np.random.default_rng(0), 3, 0.02)
    with pytest.raises(ValueError, match="positive"):
        common_offset_posterior(Delta, -s, 0.02, off)
    with pytest.raises(ValueError, match="must be"):
        common_offset_posterior(Delta[0], s, 0.02, off)
    with pytest.raises(ValueError, match="tau must be positive"):
        common_offset_prior(0.0)
    s_, n, p = pd_sheet()
    S = s_.symbol(p, s_.wavevectors).detach()
    with pytest.raises(ValueError, match="symmetric 2 x 2"):
        error_field(S, eq51_forces(s_, [(1, 0)]), torch.full((n * n - 1,), 0.01), torch.tensor([[0.0, 1.0], [0.0, 0.0]],
                    dtype=torch.float64), n, torch.Generator().manual_seed(0))
