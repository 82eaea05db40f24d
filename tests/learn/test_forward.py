"""The dynamic PD forward run (bayespd.learn.forward): patch test, energy conservation, wave speed."""
import numpy as np
import pytest

from bayespd.bonds import find_bonds, precrack
from bayespd.discretize import from_points
from bayespd.influence import Bernstein
from bayespd.learn.forward import MASS, forward_run, forward_runs, linear_in_time
from bayespd.learn.kernel import lps_params
from bayespd.materials.lps import LPS

H, DELTA = 5.0, 12.5
LAM, MU, RHO = 6.76, 5.40, 4.6  # eV/A^2 and g/mol per A^2: the graphene sheet's (docs/results.md)
PARAMS = lps_params(LAM, MU, [1.0, 2.0, 1.5, 0.5], DELTA)


def grid(nx, ny):
    g = np.stack(np.meshgrid(np.arange(nx) * H, np.arange(ny) * H, indexing="ij"), -1).reshape(-1, 2)
    p = from_points(g, np.full(len(g), H * H), h=H)
    return p.x, LPS(p, find_bonds(p, DELTA), plane="strain", influence=Bernstein(3))


def test_affine_motion_is_exact_inside_a_prescribed_frame():
    """u = t A x with a prescribed frame two horizons wide (the frame's own dilatations then see
    full families) and the interior started on v = A x: no force, the interior stays affine."""
    x, material = grid(18, 18)
    A = np.array([[1e-3, 4e-4], [2e-4, -5e-4]])
    lo, hi = x.min(0) + 2 * DELTA + H / 2, x.max(0) - 2 * DELTA - H / 2
    frame = ~((x >= lo) & (x <= hi)).all(1)
    run = forward_run(material, PARAMS, RHO, np.linspace(0, 0.5, 6), prescribed=frame,
                      moving=lambda t: t * x @ A.T, v0=x @ A.T)
    exact = 0.5 * x @ A.T
    assert np.abs(run.u[-1] - exact)[~frame].max() < 1e-12 * np.abs(exact).max()


def test_traction_free_stretch_stays_affine_between_free_edges_with_the_surface_correction():
    """Uniaxial stretch free of traction on the top and bottom edges (eps_yy = -lam / (lam + 2 mu)
    eps_xx), pulled by prescribed side layers two horizons wide, the rest started on v = A x: with
    eq 3.18 (``surface=True``) no node feels a force and the motion stays affine to rounding; the
    uncorrected LPS pulls the free edges off it (by 3e-3 of |u| here, 1e10 times more)."""
    x, material = grid(18, 12)
    A = np.array([[1e-3, 0.0], [0.0, -LAM / (LAM + 2 * MU) * 1e-3]])
    layer = (x[:, 0] < x[:, 0].min() + 2 * DELTA) | (x[:, 0] > x[:, 0].max() - 2 * DELTA)
    frames = np.linspace(0, 0.5, 6)
    exact = 0.5 * x @ A.T
    off = []
    for surface in (True, False):
        run = forward_run(material, PARAMS, RHO, frames, prescribed=layer, moving=lambda t: t * x @ A.T, v0=x @ A.T,
                          surface=surface)
        off.append(np.abs(run.u[-1] - exact)[~layer].max() / np.abs(exact).max())
    assert off[0] < 1e-12
    assert off[1] > 1e-4


def test_energy_is_conserved_to_second_order_in_dt():
    """Free body, no damage: Verlet's energy error is bounded and O(dt^2): halving dt divides
    its largest value over the run by 4 (3.2-4.8 allowed)."""
    x, material = grid(12, 12)
    v0 = np.stack([np.sin(np.pi * x[:, 0] / 55), np.cos(np.pi * x[:, 1] / 55)], 1)
    frames = np.linspace(0, 0.6, 7)
    drift = [np.abs(r.energy / r.energy[0] - 1).max() for r in
             (forward_run(material, PARAMS, RHO, frames, v0=v0, safety=s) for s in (0.5, 0.25))]
    assert drift[0] < 0.02
    assert 3.2 < drift[0] / drift[1] < 4.8


def test_longitudinal_front_travels_at_the_p_wave_speed():
    """A velocity step on a two-horizon-wide edge layer: the half-level of the step crosses two
    mid-row stations 100 A apart at c_L = sqrt((lambda + 2 mu) / rho) (plane wave; dispersion of
    the discrete kernel and the free edges' release waves: 5 % allowed)."""
    x, material = grid(40, 30)
    layer = x[:, 0] < 2 * DELTA
    frames = np.linspace(0, 0.8, 81)
    run = forward_run(material, PARAMS, RHO, frames, prescribed=layer,
                      moving=lambda t: np.stack([np.full(len(x), t), np.zeros(len(x))], 1))
    mid = np.abs(x[:, 1] - x[:, 1].mean()) < H / 2 + 1e-9
    times = []
    for station in (50.0, 150.0):
        k = np.flatnonzero(mid & (np.abs(x[:, 0] - station) < 1e-9))[0]
        v = np.diff(run.u[:, k, 0]) / np.diff(frames)
        tm = 0.5 * (frames[1:] + frames[:-1])
        j = np.flatnonzero(v >= 0.5)[0]
        times.append(tm[j - 1] + (0.5 - v[j - 1]) / (v[j] - v[j - 1]) * (tm[j] - tm[j - 1]))
    c = np.sqrt((LAM + 2 * MU) / (MASS * RHO))
    assert abs(100.0 / (times[1] - times[0]) / c - 1) < 0.05


@pytest.mark.parametrize("eta_over_s0", [0.05, 0.8])
def test_each_bond_follows_eq_3_10_with_the_width_passed(eta_over_s0):
    """Every node prescribed on u = t A x: a bond's intact fraction at the end is eq 3.10 of its
    largest stretch, |(I + t A) xi| / |xi| - 1 at the last time or 0 (the start) for a shortened
    bond, with eta = eta_over_s0 s0 (to rounding); stretches up to 1.6 s0 reach both tails of the tanh."""
    x, material = grid(8, 8)
    A, s0 = np.array([[0.03, 0.01], [0.0, -0.01]]), 0.02
    run = forward_run(material, PARAMS, RHO, [0.0, 0.5, 1.0], s0, prescribed=np.ones(len(x), bool),
                      moving=lambda t: t * x @ A.T, eta_over_s0=eta_over_s0)
    xi = x[material.j] - x[material.i]
    stretch = np.linalg.norm(xi @ (np.eye(2) + A).T, axis=1) / np.linalg.norm(xi, axis=1) - 1
    assert stretch.max() > 1.5 * s0
    np.testing.assert_allclose(run.intact[-1], 0.5 * (1 - np.tanh((np.maximum(stretch, 0) - s0) / (eta_over_s0 * s0))), atol=1e-12)


def test_batched_runs_are_the_single_runs_bit_for_bit():
    """An edge-slit sheet pulled apart under a body force, five damage laws in batches of at most
    two on two threads (uneven batches): every run's u, phi and intact fractions equal its own
    forward_run's bit for bit, and the laws differ enough that the runs do (the cracks differ)."""
    x, material = grid(14, 10)
    material = type(material)(material.particles, precrack(material.particles, material.bonds, [[32.5, -1.0], [32.5, 17.5]]),
                              plane="strain", influence=Bernstein(3))
    pulled = (x[:, 0] < H / 2) | (x[:, 0] > x[:, 0].max() - H / 2)
    side = np.sign(x[:, 0] - x[:, 0].mean())[:, None] * np.array([1.0, 0.0])
    moving, body = (lambda t: 1.5 * t * side), (lambda t: np.full((len(x), 2), 1e-3 * t))
    s0s, widths = np.array([0.01, 0.014, 0.02, 0.014, 0.01]), np.array([0.05, 0.2, 0.8, 0.8, 0.2])
    frames = np.linspace(0.0, 0.6, 7)
    runs = forward_runs(material, PARAMS, RHO, frames, s0s, widths, pulled, moving, None, body, batch=2, threads=2)
    for run, s0, width in zip(runs, s0s, widths):
        one = forward_run(material, PARAMS, RHO, frames, s0, pulled, moving, None, body, eta_over_s0=width)
        assert run.energy is None and run.steps == one.steps
        for a, b in ((run.u, one.u), (run.phi, one.phi), (run.intact, one.intact)):
            assert np.array_equal(a, b)
    broken = [int((r.intact[-1] < 0.5).sum()) for r in runs]
    assert min(broken) > 0 and len(set(broken)) >= 3


@pytest.mark.parametrize("free_sites", ["pulled columns are collar", "all free"])
def test_batched_runs_under_eq_3_18_are_the_single_runs_bit_for_bit(free_sites):
    """The edge-slit sheet pulled by its side columns under eq 3.18 (``surface``: the sites beyond
    the pulled columns a collar moving with them, or every missing site free), three laws in
    batches of at most two on two threads: each run equals its own forward_run bit for bit (each
    copy's sites are judged at the body's own coordinates), and the two readings of the sites
    differ (the collar is seen)."""
    x, material = grid(12, 8)
    material = type(material)(material.particles, precrack(material.particles, material.bonds, [[27.5, -1.0], [27.5, 12.5]]),
                              plane="strain", influence=Bernstein(3))
    pulled = (x[:, 0] < H / 2) | (x[:, 0] > x[:, 0].max() - H / 2)
    side = np.sign(x[:, 0] - x[:, 0].mean())[:, None] * np.array([1.0, 0.0])
    lo, hi = x[:, 0].min() - H / 2, x[:, 0].max() + H / 2

    def collar(sites):
        return (sites[:, 0] > lo) & (sites[:, 0] < hi)
    surface = collar if free_sites.startswith("pulled") else True
    moving, frames = (lambda t: 2.0 * t * side), np.linspace(0.0, 0.5, 6)
    s0s, widths = np.array([0.01, 0.014, 0.02]), np.array([0.05, 0.2, 0.8])
    runs = forward_runs(material, PARAMS, RHO, frames, s0s, widths, pulled, moving, surface=surface, batch=2, threads=2)
    for run, s0, width in zip(runs, s0s, widths):
        one = forward_run(material, PARAMS, RHO, frames, s0, pulled, moving, surface=surface, eta_over_s0=width)
        for a, b in ((run.u, one.u), (run.phi, one.phi), (run.intact, one.intact)):
            assert np.array_equal(a, b)
    other = forward_run(material, PARAMS, RHO, frames, s0s[0], pulled, moving, eta_over_s0=widths[0],
                        surface=True if surface is collar else collar)
    assert np.abs(other.u[-1] - runs[0].u[-1]).max() > 1e-6 * np.abs(runs[0].u[-1]).max()


def test_prescribed_history_is_linear_between_frames():
    at = linear_in_time([0.0, 1.0, 3.0], np.array([[0.0], [2.0], [0.0]]))
    np.testing.assert_allclose([at(0.5)[0], at(2.0)[0], at(5.0)[0]], [1.0, 1.0, 0.0])
    with pytest.raises(ValueError, match="increasing"):
        linear_in_time([0.0, 0.0], np.zeros((2, 1)))


def test_bad_input_is_refused_with_the_fix():
    x, material = grid(6, 6)
    with pytest.raises(ValueError, match="moving"):
        forward_run(material, PARAMS, RHO, [0.0, 0.1], prescribed=np.ones(len(x), bool))
    with pytest.raises(ValueError, match="rho"):
        forward_run(material, PARAMS, -1.0, [0.0, 0.1])
    with pytest.raises(ValueError, match="start at t = 0"):
        forward_run(material, PARAMS, RHO, [0.1, 0.2])
    with pytest.raises(ValueError, match="eta_over_s0"):
        forward_run(material, PARAMS, RHO, [0.0, 0.1], 0.1, eta_over_s0=0.0)
    with pytest.raises(ValueError, match="one eta_over_s0 per s0"):
        forward_runs(material, PARAMS, RHO, [0.0, 0.1], [0.1, 0.2, 0.3], [0.25, 0.5])
    with pytest.raises(ValueError, match="at least one s0"):
        forward_runs(material, PARAMS, RHO, [0.0, 0.1], [])
    with pytest.raises(ValueError, match="s0 must be positive"):
        forward_runs(material, PARAMS, RHO, [0.0, 0.1], [0.1, -0.1])
