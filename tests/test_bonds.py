"""Pre-cracks: exactly the bonds crossing the segment / polygon are removed."""
import numpy as np
import pytest

import bayespd as bp
from bayespd.bonds import precrack


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
