"""bayespd.learn.dispersion: the compliance measured from the sinusoidal loads of a PD sheet is its
own symbol's inverse (the relative error Delta vanishes to rounding), and a model-error draw has
the law it states (per-entry variances, chi-square)."""
import numpy as np
import pytest
import torch
from scipy import stats

from bayespd.learn.dispersion import error_field, measured_compliance, relative_compliance_error, shell_of
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


def test_the_error_field_has_the_stated_law():
    """Delta = L^T X L read back from a draw at the wave (1, 2) (X's columns: e_hat / f_hat of its
    x and y loads there) has entries N(0, s^2 + tau^2) on the diagonal and N(0, (s^2 + tau^2) / 2)
    off it: over 400 draws each variance's chi-square statistic lies in its two-sided 99 % range
    (a 1 % false rejection each; a variance off by 25 % is rejected with power above 0.99: the
    statistic's mean moves by 100 against its sd of 28)."""
    s, n, p = pd_sheet()
    k_all = s.wavevectors
    S = s.symbol(p, k_all).detach()
    f = eq51_forces(s, [(1, 2)])
    f_hat = torch.fft.fft2(f.reshape(2, n, n, 2), dim=(1, 2))[:, 1, 2]
    L = torch.linalg.cholesky(S[1 * n + 2 - 1])  # wavevectors omit k = 0
    sd, tau, draws = 0.03, 0.02, 400
    generator = torch.Generator().manual_seed(0)
    Delta = []
    for _ in range(draws):
        e = error_field(S, f, torch.full((len(k_all),), sd), tau, n, generator)
        e_hat = torch.fft.fft2(e.reshape(2, n, n, 2), dim=(1, 2))[:, 1, 2]
        X = torch.stack([(e_hat[a] / f_hat[a, a]).real for a in (0, 1)], -1)
        Delta.append(L.T @ X @ L)
    Delta = torch.stack(Delta)
    var = sd**2 + tau**2
    for values, v in ((Delta[:, 0, 0], var), (Delta[:, 1, 1], var), (Delta[:, 0, 1], var / 2)):
        chi2 = float((values**2).sum()) / v
        assert stats.chi2.ppf(0.005, draws) < chi2 < stats.chi2.ppf(0.995, draws)
