"""Paper 004's loads: 70 training modes, self-equilibrated disks (Table 1), the pulse's peak."""
import numpy as np
import pytest

from bayespd.learn import graphene, md_loads


@pytest.fixture
def sheet():
    return graphene.sheet(41, 23, 1.42)


def test_seventy_sinusoidal_modes_with_strain_bounded_amplitudes(sheet):
    x, box = sheet
    cases = md_loads.sinusoidal_cases()
    assert len(cases) == 70 and (0, 0, 0) not in cases
    f = md_loads.sinusoidal(x, box, 1, 2, 1, 0.005)
    k = 2 * np.pi * np.hypot(1 / box[0], 2 / box[1])
    np.testing.assert_allclose(np.abs(f[:, 1]).max(), md_loads.amplitude(0.005, k), rtol=1e-2)
    assert np.abs(f.sum(0)).max() < 1e-10 * np.abs(f).sum()  # a whole number of periods on the lattice
    with pytest.raises(ValueError, match="uniform force"):
        md_loads.sinusoidal(x, box, 0, 0, 0, 0.005)
    with pytest.raises(ValueError, match="linear range"):
        md_loads.amplitude(0.05, k)


def test_unseen_waves_are_off_the_training_orbits_and_inside_their_range(sheet):
    """Ten loads, none on a training orbit (max(n1, n2) > 5), both axes on the axis waves, and
    |k| at most 1.05 times the training set's largest ((5, 5)): interpolation in |k| h."""
    x, box = sheet
    cases = md_loads.unseen_cases()
    assert len(set(cases)) == 10 and not set((a, b) for a, b, _ in cases) & set((a, b) for a, b, _ in
                                                                                 md_loads.sinusoidal_cases())
    assert {(6, 0, 0), (6, 0, 1), (0, 6, 0), (0, 6, 1)} <= set(cases)
    wavenumber = [np.hypot(*(2 * np.pi * np.array([a, b]) / box)) for a, b, _ in cases]
    assert max(wavenumber) < 1.05 * np.hypot(*(2 * np.pi * np.array([5, 5]) / box))
    with pytest.raises(ValueError, match="largest mode"):
        md_loads.unseen_cases(0)


def test_blind_waves_are_new_to_both_sets(sheet):
    """Sixteen loads on eight mixed waves, each along both axes, none on a training orbit nor
    among the unseen set's, |k| at most 1.1 times the training set's largest (1.09 at (3, 7) on the sheet)."""
    x, box = sheet
    cases = md_loads.blind_cases()
    waves = {(a, b) for a, b, _ in cases}
    assert len(set(cases)) == 16 and len(waves) == 8 and all(max(w) > 5 and min(w) > 0 for w in waves)
    assert not waves & {(a, b) for a, b, _ in md_loads.sinusoidal_cases()}
    assert not set(cases) & set(md_loads.unseen_cases())
    wavenumber = [np.hypot(*(2 * np.pi * np.array([a, b]) / box)) for a, b, _ in cases]
    assert max(wavenumber) < 1.1 * np.hypot(*(2 * np.pi * np.array([5, 5]) / box))
    with pytest.raises(ValueError, match="largest mode"):
        md_loads.blind_cases(0)


@pytest.mark.parametrize("case", range(1, 11))
def test_disk_loads_are_self_equilibrated(sheet, case):
    """+1 disk at the centre, -1 across the periodic boundary: the net force is the lattice
    quadrature error of two equal integrals, a few percent of one disk's total at most."""
    x, box = sheet
    f = md_loads.disks(x, box, case, 0.005)
    c1, c2, p, radius = md_loads.TABLE_1[case - 1]
    one_disk = np.abs(f).sum() / 2
    assert np.abs(f.sum(0)).max() < 0.03 * one_disk
    assert np.abs(f[:, 0 if c1 else 1]).max() > 0 and np.abs(f[:, 1 if c1 else 0]).max() == 0


def test_pulse_peaks_at_tr_ln2_and_opens_the_slit():
    x = np.array([[25.0, -50.0], [-25.0, -50.0], [25.0, 50.0]])
    f = md_loads.pulse(x, np.zeros(2), 0.5 * np.log(2), 2.0, 0.5, 100.0)
    np.testing.assert_allclose(f[:, 0], 2.0 / 4 * np.sin(np.pi / 4) * np.array([1.0, -1.0, np.exp(-1.0)]), rtol=1e-12)
    assert (f[:, 1] == 0).all()
