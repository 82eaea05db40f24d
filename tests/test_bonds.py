"""bayespd/bonds.py: the neighbour search at delta_max against brute force, partial volumes
(continuous in delta, conserving the family's area to O(h)), refused horizons, and
pre-cracks (exactly the bonds crossing the segment / polygon are removed)."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.bonds import _lattice_pairs, check_horizon, partial_volume, precrack
from bayespd.influence import Bernstein


def brute_force_2d(a, b, c0, c1):
    """Intersection of segments by solving a + s (b - a) = c0 + t (c1 - c0) for (s, t)."""
    out = np.zeros(len(a), dtype=bool)
    for k in range(len(a)):
        M = np.column_stack([b[k] - a[k], c0 - c1])
        if abs(np.linalg.det(M)) < 1e-12:
            continue
        s, t = np.linalg.solve(M, c0 - a[k])
        out[k] = 0 < s < 1 and 0 <= t <= 1
    return out


def test_segment_cuts_exactly_the_crossing_bonds():
    p = bp.grid_2d(12.0, 12.0, 1.0)
    bonds = bp.find_bonds(p, 3.0)
    crack = np.array([[6.0, -1.0], [6.3, 7.2]])  # between particle columns, slightly slanted
    cut = precrack(p, bonds, crack)
    expected = brute_force_2d(p.x[bonds.i], p.x[bonds.j], crack[0], crack[1])
    assert bonds.n - cut.n == expected.sum() > 0
    kept = set(zip(cut.i.tolist(), cut.j.tolist()))
    assert all(((i, j) in kept) != e for i, j, e in zip(bonds.i.tolist(), bonds.j.tolist(), expected))


def test_through_crack_separates_the_body():
    """A crack across the whole plate leaves the right half floating: refused up front."""
    p = bp.grid_2d(10.0, 6.0, 1.0)
    bonds = precrack(p, bp.find_bonds(p, 2.5), [[5.0, -1.0], [5.0, 7.0]])
    with pytest.raises(ValueError, match="30 particle.*no Dirichlet region"):
        bp.Scene(bp.LPS(p, bonds), [bp.Dirichlet.layer(p, "left", 2.5)], [bp.Load(p.layer("right", 1.0), (1.0, 0.0))])


def test_edge_crack_opens_under_tension():
    """Mode I: with an edge crack, the faces separate; the jump in u_y across the crack
    mouth exceeds the uncracked stretch over the same gauge by an order of magnitude."""
    p = bp.grid_2d(20.0, 20.0, 1.0)
    params = {"K": 3000.0, "G": 1400.0, "delta": 2.5}
    jumps = []
    for crack in (None, [[-1.0, 10.0], [8.0, 10.0]]):
        bonds = bp.find_bonds(p, 2.5)
        bonds = bonds if crack is None else precrack(p, bonds, crack)
        scene = bp.Scene(bp.LPS(p, bonds), [bp.Dirichlet.layer(p, "bottom", 2.5)],
                         [bp.Load(p.layer("top", 1.0), (0.0, 200.0))])
        u = scene.solve(params)
        above = np.flatnonzero(np.isclose(p.x[:, 0], 3.5) & np.isclose(p.x[:, 1], 10.5))[0]
        below = np.flatnonzero(np.isclose(p.x[:, 0], 3.5) & np.isclose(p.x[:, 1], 9.5))[0]
        jumps.append(float(u[above, 1] - u[below, 1]))
    assert jumps[1] > 10 * jumps[0] > 0


def test_polygon_cuts_exactly_the_crossing_bonds_3d():
    p = bp.grid_3d(6.0, 6.0, 6.0, 1.0)
    bonds = bp.find_bonds(p, 2.0)
    square = np.array([[3.0, -1.0, -1.0], [3.0, 3.2, -1.0], [3.0, 3.2, 7.0], [3.0, -1.0, 7.0]])
    cut = precrack(p, bonds, square)
    a, b = p.x[bonds.i], p.x[bonds.j]
    s = (3.0 - a[:, 0]) / (b[:, 0] - a[:, 0] + 1e-300)
    y = a[:, 1] + s * (b[:, 1] - a[:, 1])
    expected = ((a[:, 0] - 3.0) * (b[:, 0] - 3.0) < 0) & (y < 3.2)
    assert bonds.n - cut.n == expected.sum() > 0


def test_bad_cracks():
    p = bp.grid_3d(4.0, 4.0, 4.0, 1.0)
    bonds = bp.find_bonds(p, 1.5)
    with pytest.raises(ValueError, match="not planar"):
        precrack(p, bonds, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.5]])
    with pytest.raises(ValueError, match="collinear"):
        precrack(p, bonds, [[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    q = bp.grid_2d(4.0, 4.0, 1.0)
    with pytest.raises(ValueError, match="segment"):
        precrack(q, bp.find_bonds(q, 1.5), [[0, 0], [1, 1], [2, 2]])
    with pytest.raises(ValueError, match="NaN"):
        precrack(q, bp.find_bonds(q, 1.5), [[0, 0], [np.nan, 1]])


def test_smooth_partial_volume_is_c1_in_delta():
    """The smoothstep ramp has the linear one's values at the ends and mid-point (0, 1/2, 1)
    and the same mean 1/2 over the ramp; its derivative in delta is continuous (0 at both
    ends, where the linear ramp's jumps by 1/h); an unknown rule is refused."""
    from bayespd.bonds import partial_volume

    h, length = 0.5, torch.tensor(1.3)
    ends = torch.tensor([length - h / 2, length + h / 2], dtype=torch.float64)
    for rule, jump in (("linear", 1 / h), ("smooth", 0.0)):
        slopes = []
        for side in (-1e-9, 1e-9):
            d = (ends + side).requires_grad_()
            slopes.append(torch.autograd.grad(partial_volume(length, d, h, rule).sum(), d)[0])
        assert torch.allclose((slopes[1] - slopes[0]).abs(), torch.tensor([jump, jump], dtype=torch.float64), atol=1e-6)
    t = torch.linspace(0, 1, 10001, dtype=torch.float64)
    w = partial_volume(length, length - h / 2 + t * h, h, "smooth")
    assert float(w[0]) == 0.0 and float(w[-1]) == 1.0 and float(w[5000]) == pytest.approx(0.5, abs=1e-12)
    assert float(torch.trapezoid(w, t)) == pytest.approx(0.5, abs=1e-8)
    with pytest.raises(ValueError, match="partial-volume rule"):
        bp.find_bonds(bp.grid_2d(4.0, 4.0, 1.0), 2.0, rule="cubic")


def brute_force_pairs(x, radius):
    """Every pair (i < j) closer than ``radius``, by an O(N^2) double loop over distances."""
    d = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=-1)
    i, j = np.nonzero(np.triu(d < radius, k=1))
    return set(zip(i.tolist(), j.tolist()))


@pytest.mark.parametrize("dim", [2, 3])
def test_find_bonds_finds_every_pair_once_against_brute_force(dim):
    """On jittered (irregular) points: the pairs are exactly those closer than delta_max + h/2
    (an O(N^2) search), each once with i < j, sorted by (i, j); xi = x_j - x_i and length =
    |xi| to rounding."""
    rng = np.random.default_rng(dim)
    g = bp.grid_2d(8.0, 6.0, 1.0) if dim == 2 else bp.grid_3d(4.0, 4.0, 3.0, 1.0)
    x = g.x + rng.uniform(-0.3, 0.3, g.x.shape)
    p = bp.from_points(x, g.volume, h=1.0)
    bonds = bp.find_bonds(p, 2.2)
    pairs = list(zip(bonds.i.tolist(), bonds.j.tolist()))
    assert len(pairs) == len(set(pairs)) == bonds.n
    assert set(pairs) == brute_force_pairs(x, 2.2 + 0.5)
    assert np.all(bonds.i < bonds.j) and pairs == sorted(pairs)
    np.testing.assert_array_equal(bonds.xi, x[bonds.j] - x[bonds.i])
    np.testing.assert_allclose(bonds.length, np.linalg.norm(bonds.xi, axis=1), rtol=1e-15)
    assert bonds.h == 1.0 and bonds.delta_max == 2.2 and bonds.rule == "linear"


@pytest.mark.parametrize("particles, m", [(bp.grid_2d(12.0, 9.0, 1.0), m) for m in (1.0, 2.0, 3.0, 4.2)]
                         + [(bp.grid_2d(7.5, 12.5, 0.5, origin=(-3.0, 1.0)), 3.0), (bp.grid_3d(6.0, 5.0, 4.0, 1.0), 2.0),
                            (bp.grid_3d(3.0, 2.5, 2.0, 0.25, origin=(1.0, 2.0, 3.0)), 2.2)])
def test_a_box_lattice_gets_the_pairs_by_stencil_and_they_are_the_searchs(particles, m):
    """On ``grid_2d`` / ``grid_3d`` boxes (either axis order, off-origin, a horizon between lattice
    distances) the stencil path finds the brute-force pairs, sorted by (i, j)."""
    pairs = _lattice_pairs(particles.x, particles.h, (m + 0.5) * particles.h)
    assert pairs is not None
    assert list(zip(*(a.tolist() for a in pairs))) == sorted(brute_force_pairs(particles.x, (m + 0.5) * particles.h))


def test_what_is_not_a_box_lattice_goes_to_the_search():
    """Jittered, shuffled or non-box point sets, and a horizon whose radius equals a lattice distance
    (m = 2.5: 3 h, a tie the k-d tree's rounding decides), are left to the k-d tree; find_bonds then
    gives the same pairs as on the lattice itself wherever there is no tie."""
    p = bp.grid_2d(10.0, 8.0, 1.0)
    rng = np.random.default_rng(0)
    shuffled = rng.permutation(p.n)
    corner = p.x.sum(1) < 12
    for x in (p.x + rng.normal(0.0, 1e-3, p.x.shape), p.x[shuffled], p.x[corner]):
        assert _lattice_pairs(x, 1.0, 2.5) is None
    assert _lattice_pairs(p.x, 1.0, 3.0) is None
    moved = bp.find_bonds(bp.from_points(p.x[shuffled], p.volume, h=1.0), 2.0)
    on = bp.find_bonds(p, 2.0)
    assert {(min(a, b), max(a, b)) for a, b in zip(shuffled[moved.i], shuffled[moved.j])} == set(zip(on.i, on.j))


def test_neighbour_counts_are_symmetric_on_a_lattice():
    """Each interior particle of a square lattice at delta_max = 2 (+ h/2 = 2.5) has the 20
    neighbours with |xi|^2 in {1, 2, 4, 5}, and the bond graph is symmetric: i's neighbours
    include j exactly when j's include i (one bond serves both)."""
    p = bp.grid_2d(9.0, 9.0, 1.0)
    bonds = bp.find_bonds(p, 2.0)
    degree = np.bincount(bonds.i, minlength=p.n) + np.bincount(bonds.j, minlength=p.n)
    interior = np.all(np.abs(p.x - 4.5) < 2.6, axis=1)
    assert np.all(degree[interior] == 20)
    A = np.zeros((p.n, p.n), dtype=int)
    np.add.at(A, (bonds.i, bonds.j), 1)
    np.add.at(A, (bonds.j, bonds.i), 1)
    assert np.array_equal(A, A.T) and A.max() == 1 and np.trace(A) == 0


@pytest.mark.parametrize("rule", ["linear", "smooth"])
@pytest.mark.parametrize("delta", [2.0, 2.7, 3.0])
def test_partial_volumes_sum_to_the_family_area_within_order_h(delta, rule):
    """sum_j w_j h^2 over a lattice family (plus the particle's own cell) approximates the
    disc pi delta^2; both ramps have mean 1/2 over the cells the circle cuts, so the error is
    bounded by a fraction of that band's area 2 pi delta h: we assert |error| <= pi delta h / 2
    at h = 1, 1/2, ..., 1/16 (O(h); measured at most 0.545 = 0.09 pi delta h, linear rule,
    delta = 2, h = 1)."""
    for k in range(5):
        h = 0.5**k
        n = int(np.ceil((delta + h) / h))
        offsets = h * np.stack(np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1)), -1).reshape(-1, 2)
        length = torch.as_tensor(np.linalg.norm(offsets, axis=1))
        length = length[length > 0]
        area = float(partial_volume(length, delta, h, rule).sum()) * h * h + h * h
        assert abs(area - np.pi * delta**2) <= np.pi * delta * h / 2, (h, area)


def test_weights_are_a_continuous_monotone_ramp_in_delta():
    """w(delta) = clamp((delta + h/2 - |xi|) / h, 0, 1): 1 for |xi| <= delta - h/2, 0 for
    |xi| >= delta + h/2, nondecreasing in delta, Lipschitz with constant 1/h (so continuous),
    and its autograd derivative is 1/h inside the ramp, 0 outside."""
    p = bp.grid_2d(8.0, 8.0, 0.5)
    bonds = bp.find_bonds(p, 2.0)
    deltas = np.linspace(0.5, 2.0, 301)
    W = np.stack([bonds.weight(d).numpy() for d in deltas])
    assert np.all(np.diff(W, axis=0) >= 0)
    assert np.abs(np.diff(W, axis=0)).max() <= (deltas[1] - deltas[0]) / 0.5 * (1 + 1e-12)
    L = bonds.length
    for d, w in zip(deltas[::50], W[::50]):
        assert np.all(w[L <= d - 0.25] == 1.0) and np.all(w[L >= d + 0.25] == 0.0)
    d = torch.tensor(1.3, requires_grad=True)
    (g,) = torch.autograd.grad(bonds.weight(d).sum(), d)
    inside = (L > 1.3 - 0.25) & (L < 1.3 + 0.25)
    assert float(g) == pytest.approx(inside.sum() / 0.5, rel=1e-12)
    assert np.all(bonds.weight(2.0).numpy() > 0)  # every bond kept contributes at delta_max


def test_without_keeps_the_complement():
    p = bp.grid_2d(5.0, 5.0, 1.0)
    bonds = bp.find_bonds(p, 1.5)
    remove = np.arange(bonds.n) % 3 == 0
    kept = bonds.without(remove)
    assert kept.n == bonds.n - remove.sum()
    np.testing.assert_array_equal(kept.i, bonds.i[~remove])
    np.testing.assert_array_equal(kept.xi, bonds.xi[~remove])
    assert (kept.h, kept.delta_max, kept.rule) == (bonds.h, bonds.delta_max, bonds.rule)


def test_bad_horizons_name_the_fix():
    p = bp.grid_2d(5.0, 5.0, 1.0)
    with pytest.raises(ValueError, match="must be at least the grid spacing"):
        bp.find_bonds(p, 0.9)
    with pytest.raises(ValueError, match="smaller than the grid spacing.*delta >= h"):
        check_horizon(0.5, 1.0, 3.0)
    with pytest.raises(ValueError, match="exceeds delta_max.*larger delta_max"):
        bp.find_bonds(p, 2.0).weight(2.1)
    with pytest.raises(ValueError, match="finite"):
        check_horizon(float("nan"), 1.0, 3.0)
    check_horizon(3.0 * (1 + 1e-13), 1.0, 3.0)  # rounding above delta_max is accepted


@pytest.mark.parametrize("crack, match", [
    ([[2.0, 2.5], [2.0, 2.5]], r"pre-crack \[\[2.0, 2.5\], \[2.0, 2.5\]\] has zero length"),
    ([[20.0, 2.5], [30.0, 2.5]], r"cuts no bond: it lies outside the body \[\[0.0, 0.0\], \[10.0, 6.0\]\]"),
    ([[0.0, np.inf], [1.0, 2.0]], "crack coordinates contains NaN or inf"),
])
def test_a_precrack_that_cuts_nothing_is_refused(crack, match):
    p = bp.grid_2d(10.0, 6.0, 1.0)
    with pytest.raises(ValueError, match=match):
        precrack(p, bp.find_bonds(p, 2.5), crack)


def test_a_tiny_precrack_between_rows_cuts_the_bonds_through_it():
    """1e-3 h long, between two rows: only the bonds passing through it go, all vertical-ish."""
    p = bp.grid_2d(10.0, 6.0, 1.0)
    bonds = bp.find_bonds(p, 2.5)
    cut = precrack(p, bonds, [[5.0, 3.0], [5.001, 3.0]])
    assert 0 < bonds.n - cut.n < 10


def test_infinite_delta_max_is_refused():
    p = bp.grid_2d(4.0, 4.0, 1.0)
    with pytest.raises(ValueError, match="delta_max contains NaN or inf.*finite horizon"):
        bp.find_bonds(p, np.inf)


def test_kinks_are_where_a_bond_length_crosses_delta_or_delta_plus_minus_half_h():
    """On a unit lattice the bond lengths are sqrt(i^2 + j^2): the kinks in [2, 3.2] are those and
    those +- 1/2. The summed partial volumes have a zero second difference between the +- 1/2 kinks
    (to rounding) and one of at least a bond's slope change times the step across each (the step
    1e-3 is below the smallest gap, 0.024); the summed influence-weighted volumes bend at the lengths
    themselves (a Bernstein omega = (r / delta)^2, clamped to 1 beyond delta)."""
    bonds = bp.find_bonds(bp.grid_2d(12.0, 12.0, 1.0), 3.5)
    lengths = np.sqrt([i * i + j * j for i in range(5) for j in range(5) if i or j])
    expected = np.unique(np.round(np.concatenate([lengths - 0.5, lengths, lengths + 0.5]), 12))
    kinks = bonds.kinks(2.0, 3.2)
    np.testing.assert_allclose(kinks, expected[(expected >= 2.0) & (expected <= 3.2)], atol=1e-9)

    def bend(f, delta, step=1e-3):
        w = [f(d) for d in (delta - step, delta, delta + step)]
        return abs(w[0] - 2 * w[1] + w[2])

    volume = lambda d: float(bonds.weight(d).sum())  # noqa: E731
    ramp = np.unique(np.round(np.concatenate([lengths - 0.5, lengths + 0.5]), 12))
    ramp = ramp[(ramp >= 2.0) & (ramp <= 3.2)]
    assert all(bend(volume, k) > 0.9e-3 for k in ramp)
    assert all(bend(volume, m) < 1e-9 for m in (kinks[1:] + kinks[:-1]) / 2)
    length = torch.as_tensor(bonds.length)
    omega = Bernstein(2)
    influence = lambda d: float((bonds.weight(d) * omega(length, d, {"D": torch.tensor([0.0, 0.0, 1.0])})).sum())  # noqa: E731
    at_lengths = [k for k in kinks if np.isclose(lengths, k).any()]
    assert at_lengths and all(bend(influence, k) > 1e-4 for k in at_lengths)
