"""s0 by simulation (bayespd.learn.discrepancy): the metric, and s0 recovered from PD data made on
a twice finer grid (no inverse crime)."""
import numpy as np
import pytest

from bayespd.bonds import crossing, find_bonds, precrack
from bayespd.discretize import from_points
from bayespd.influence import Bernstein
from bayespd.learn.discrepancy import count_damage, learn_s0, relative_error, relative_mse
from bayespd.learn.forward import MASS, forward_run
from bayespd.learn.kernel import lps_params
from bayespd.materials.lps import LPS

DELTA, S0, W = 2.5, 0.04, 10.0


def test_relative_error_is_the_time_average_of_frame_ratios():
    data = np.zeros((3, 2, 2))
    data[1, 0, 0], data[2, 1, 1] = 2.0, 4.0
    pred = data.copy()
    pred[1, 0, 0], pred[2, 1, 1] = 3.0, 2.0  # ratios 1/2 and 1/2; frame 0 (zero data) is skipped
    assert relative_error(pred, data) == pytest.approx(0.5, rel=1e-15)
    assert relative_error(pred, data, np.array([True, False])) == pytest.approx(0.5, rel=1e-15)
    with pytest.raises(ValueError, match="zero at every frame"):
        relative_error(pred[:1], data[:1])
    with pytest.raises(ValueError, match="one shape"):
        relative_error(pred[:, :1], data)


def test_relative_mse_averages_the_squared_frame_ratios():
    """Frame ratios 1/2 and 1/4 (frame 0, zero data, skipped): E2 = (1/4 + 1/16) / 2."""
    data = np.zeros((3, 2))
    data[1, 0], data[2, 1] = 2.0, 4.0
    pred = data.copy()
    pred[1, 0], pred[2, 1] = 3.0, 3.0
    assert relative_mse(pred, data) == pytest.approx((0.25 + 0.0625) / 2, rel=1e-15)
    assert relative_error(pred, data) == pytest.approx((0.5 + 0.25) / 2, rel=1e-15)


def test_count_damage_is_eq_5_4_on_a_square_grid():
    """Unit grid 5 x 5, delta = 1.5: the centre node has 8 bonds within delta (4 at 1, 4 at
    sqrt 2) and the partial-volume bonds at 2 (<= delta + h/2) do not count. Cutting two of the
    centre's bonds within delta and every bond at 2: phi = 2/8 at the centre, 1/8 at the two
    (interior) nodes across the cut bonds, 0 elsewhere; half-broken bonds (gamma = 1/2) count half."""
    g = np.arange(5.0)
    x = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    bonds = find_bonds(from_points(x, np.ones(25), h=1.0), 1.5)
    centre = 12
    intact = np.ones(len(bonds.i))
    assert (bonds.length > 1.5).any(), "no partial-volume bond beyond delta: the test does not test"
    intact[bonds.length > 1.5] = 0.0
    cut = np.flatnonzero(((bonds.i == centre) | (bonds.j == centre)) & (bonds.length <= 1.5))[:2]
    intact[cut] = 0.0
    other = np.setdiff1d(np.r_[bonds.i[cut], bonds.j[cut]], [centre])
    phi = count_damage(25, bonds.i, bonds.j, bonds.length, 1.5, np.stack([intact, 0.5 * intact + 0.5]))
    assert phi[0, centre] == pytest.approx(2 / 8, rel=1e-15) and phi[1, centre] == pytest.approx(1 / 8, rel=1e-15)
    untouched = np.setdiff1d(np.arange(25), np.r_[centre, other])
    assert np.all(phi[0, untouched] == 0.0)
    assert len(other) == 2 and np.allclose(phi[0, other], 1 / 8, rtol=1e-15)
    with pytest.raises(ValueError, match="no bond within delta"):
        count_damage(25, bonds.i, bonds.j, bonds.length, 0.5, intact)


def test_count_damage_counts_a_pre_cracks_bonds_as_broken_when_passed():
    """Eq 5.4 as printed sums over all of B_delta, so a slit's bonds count as lost. Unit grid 5 x 5,
    delta = 1.5, a slit at x = 1.5 from below the sheet to y = 2.25 cuts the horizontal bonds of
    rows 0-2 and the diagonals crossing it at y = 0.5 and 1.5. By hand: node (1, 1) loses 3 of its
    8 bonds, (1, 2) 2 of 8 (its diagonal to (2, 3) crosses at 2.5, above the slit), the edge node
    (1, 0) 2 of 5; column 4 nothing. Without ``cut`` every node is intact."""
    g = np.arange(5.0)
    x = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)  # node (a, b) at index 5 a + b
    particles = from_points(x, np.ones(25), h=1.0)
    bonds = find_bonds(particles, 1.5)
    slit = crossing(particles, bonds, [[1.5, -1.0], [1.5, 2.25]])
    kept, lost = bonds.without(slit), bonds.without(~slit)
    intact = np.ones((2, len(kept.i)))
    phi = count_damage(25, kept.i, kept.j, kept.length, 1.5, intact, cut=(lost.i, lost.j, lost.length))
    assert phi.shape == (2, 25) and np.array_equal(phi[0], phi[1])
    assert phi[0, 6] == pytest.approx(3 / 8, rel=1e-15) and phi[0, 7] == pytest.approx(2 / 8, rel=1e-15)
    assert phi[0, 5] == pytest.approx(2 / 5, rel=1e-15) and np.all(phi[0, 20:] == 0.0)
    assert np.all(count_damage(25, kept.i, kept.j, kept.length, 1.5, intact) == 0.0)
    assert len(precrack(particles, bonds, [[1.5, -1.0], [1.5, 2.25]]).i) == len(kept.i)


def test_brent_finds_the_minimum_of_a_smooth_discrepancy_in_log_s0():
    fit = learn_s0(lambda s: 1.0 if s is None else (np.log(s / 0.07)) ** 2 + 0.1, bounds=(0.01, 1.0), xatol=1e-4)
    assert fit.s0 == pytest.approx(0.07, rel=1e-3) and fit.error_intact == 1.0
    with pytest.raises(ValueError, match="low < high"):
        learn_s0(lambda s: 0.0, bounds=(1.0, 0.1))


def plate(h):
    """A W x W plate with a vertical edge slit 3 long up from the lower edge, between node columns."""
    g = np.arange(0, W + h / 2, h)
    x = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    p = from_points(x, np.full(len(x), h * h), h=h)
    bonds = precrack(p, find_bonds(p, DELTA), [[W / 2 - 0.25, -1.0], [W / 2 - 0.25, 3.0]])
    return x, LPS(p, bonds, plane="strain", influence=Bernstein(2))


def pulled(h, s0, frames):
    """Side layers (one horizon) pulled apart at a speed falling with height (the MD loading)."""
    x, material = plate(h)
    rate = 0.012 * (1.0 - x[:, 1] / W)
    side = np.sign(x[:, 0] - W / 2 + 0.25)
    layer = np.abs(x[:, 0] - W / 2) > W / 2 - DELTA
    edge = np.stack([side * rate, 0 * rate], 1)
    v0 = np.stack([rate * (x[:, 0] - W / 2) / (W / 2), 0 * rate], 1)
    run = forward_run(material, lps_params(1.0, 1.0, [1.0, 2.0, 1.0], DELTA), 1 / MASS, frames, s0, layer,
                      lambda t: edge * t, v0=v0)
    return x, layer, run


@pytest.mark.slow
def test_s0_is_recovered_from_a_finer_grid_run():
    """Data: the h = 0.5 run (delta = 5h) at s0 = 0.04, read at the h = 1 nodes; fit on the h = 1
    grid (delta = 2.5h). The crack crosses the plate, so s0 is identified; the grids' different
    discretisation error leaves a bias, 10 % allowed (measured: 3 %)."""
    frames = np.linspace(0, 40, 21)
    xf, _, fine = pulled(0.5, S0, frames)
    assert (fine.phi[-1] > 0.3).sum() > 20  # the crack ran
    on_coarse = (np.round(xf * 2).astype(int) % 2 == 0).all(1)
    data = fine.u[:, on_coarse]

    def discrepancy(s0):
        _, layer, run = pulled(1.0, s0, frames)
        return relative_error(run.u, data, ~layer)

    fit = learn_s0(discrepancy, bounds=(0.01, 0.3), xatol=0.02)
    assert abs(fit.s0 / S0 - 1) < 0.10
    assert fit.error < 0.7 * fit.error_intact
