"""bayespd/reference/fem.py: the scikit-fem reference (probes, Betti reciprocity, the
isotropic Voigt tensors, graded axes, refused input)."""
import numpy as np
import pytest
import scipy.sparse as sp

pytest.importorskip("skfem")

from bayespd.linalg.amg import v_cycle  # noqa: E402
from bayespd.reference.fem import (BodyLoad, Region, Support, graded_axis, isotropic_stiffness,  # noqa: E402
                                   solve_box, spd_solve)


@pytest.mark.parametrize("dim", [2, 3])
def test_probes_interpolate_quadratics_exactly(dim):
    """Q2 contains every quadratic: evaluating its nodal interpolant at points is exact."""
    extent = (4.0, 2.0, 2.0)[:dim]
    fe = solve_box(extent, 1.0, 1000.0, 0.3, [Support(Region((0.0,) * dim, (1.0,) + extent[1:]), (0.0,) * dim)],
                   [BodyLoad(Region((3.0,) + (0.0,) * (dim - 1), extent), (1.0,) + (0.0,) * (dim - 1))],
                   order=2, plane="stress" if dim == 2 else None, grading=1)
    rng = np.random.default_rng(0)
    A = rng.normal(size=(dim, dim, dim))

    def field(x):  # (n, dim) -> (n, dim): u_c = sum_ab A_cab x_a x_b + x_c
        return np.einsum("cab,na,nb->nc", A, x, x) + x

    for c, idx in enumerate(fe.basis.split_indices()):
        fe.u[idx] = field(fe.basis.doflocs[:, idx].T)[:, c]
    points = rng.uniform(0, 1, size=(50, dim)) * extent
    points[:3] = [np.zeros(dim), np.array(extent), 0.5 * np.array(extent)]  # corner, corner, node
    np.testing.assert_allclose(fe.at(points), field(points), rtol=1e-11, atol=1e-11)

def region_mean(fe, region, points_per_axis=3):
    """Mean of the FE field over an aligned region by tensor Gauss-Legendre quadrature per
    cell (3 points per axis integrate a Q2 field exactly)."""
    g, w = np.polynomial.legendre.leggauss(points_per_axis)
    pts, wts = [], []
    for a, (lo, hi) in enumerate(zip(region.lo, region.hi)):
        nodes = fe.axes[a][(fe.axes[a] >= lo - 1e-12) & (fe.axes[a] <= hi + 1e-12)]
        left, right = nodes[:-1, None], nodes[1:, None]
        pts.append(((left + right) / 2 + (right - left) / 2 * g).ravel())
        wts.append(((right - left) / 2 * w).ravel())
    mesh = np.stack(np.meshgrid(*pts, indexing="ij"), -1).reshape(-1, len(pts))
    weight = np.prod(np.stack(np.meshgrid(*wts, indexing="ij"), -1).reshape(-1, len(wts)), axis=1)
    return weight @ fe.at(mesh) / weight.sum()


@pytest.mark.parametrize("order", [1, 2])
def test_betti_reciprocity(order):
    """Maxwell-Betti: the discrete operator is symmetric, so the work of load A on the
    displacement of load B equals that of B on A's, f_A . u_B = f_B . u_A, where f . u =
    F . (mean of u over the load's region) for a uniform body force (the region is aligned
    with the mesh, so the assembled load is exact); to the solver's rounding (1e-12)."""
    support = [Support(Region((0.0, 0.0), (1.0, 4.0)), (0.0, 0.0))]
    A = BodyLoad(Region((6.0, 0.0), (8.0, 1.0)), (0.3, -1.0))
    B = BodyLoad(Region((3.0, 3.0), (5.0, 4.0)), (1.0, 0.5))
    fe_a, fe_b = (solve_box((8.0, 4.0), 1.0, 1000.0, 0.3, support, [load], order=order, thickness=2.0)
                  for load in (A, B))
    ab = np.dot(A.force, region_mean(fe_b, A.region))
    ba = np.dot(B.force, region_mean(fe_a, B.region))
    assert abs(ab) > 1e-4
    assert ab == pytest.approx(ba, rel=1e-11)


def test_loads_superpose_and_scale_with_one_over_thickness():
    """Linear elasticity: u(A + 2B) = u(A) + 2 u(B) (1e-12); the body force is F / (|R| t), so
    doubling the thickness halves u."""
    support = [Support(Region((0.0, 0.0), (1.0, 2.0)), (0.0, 0.0))]
    A = BodyLoad(Region((3.0, 0.0), (4.0, 2.0)), (1.0, 0.0))
    B = BodyLoad(Region((2.0, 1.0), (4.0, 2.0)), (0.0, -2.0))
    B2 = BodyLoad(B.region, (0.0, -4.0))

    def solve(loads, t=1.0):
        return solve_box((4.0, 2.0), 0.5, 200.0, 0.25, support, loads, order=2, thickness=t).u

    ua, ub = solve([A]), solve([B])
    np.testing.assert_allclose(solve([A, B2]), ua + 2 * ub, rtol=0, atol=1e-12 * np.abs(ub).max())
    np.testing.assert_allclose(solve([A], t=2.0), ua / 2, rtol=0, atol=1e-13 * np.abs(ua).max())


def test_isotropic_stiffness_closed_forms():
    """Plane stress: E / (1 - nu^2) [[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]]; plane strain
    and 3D: lambda = E nu / ((1 + nu)(1 - 2 nu)), mu = E / (2 (1 + nu)); the 3D tensor inverts
    the compliance (1/E)[[1, -nu, -nu], ...] with shear compliance 1 / mu; all to 1e-12."""
    E, nu = 4000.0, 0.3
    stress = E / (1 - nu**2) * np.array([[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]])
    np.testing.assert_allclose(isotropic_stiffness(E, nu, 2, "stress"), stress, rtol=1e-12, atol=1e-9)
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    strain = np.array([[lam + 2 * mu, lam, 0], [lam, lam + 2 * mu, 0], [0, 0, mu]])
    np.testing.assert_allclose(isotropic_stiffness(E, nu, 2, "strain"), strain, rtol=1e-12, atol=1e-9)
    S = np.zeros((6, 6))
    S[:3, :3] = -nu / E
    np.fill_diagonal(S[:3, :3], 1 / E)
    S[3:, 3:] = np.eye(3) / mu
    np.testing.assert_allclose(isotropic_stiffness(E, nu, 3, None) @ S, np.eye(6), atol=1e-12)
    with pytest.raises(ValueError, match="plane must be"):
        isotropic_stiffness(E, nu, 2, None)


def test_region_membership_distance_and_measure():
    """A closed box: faces belong to it; the distance is Euclidean to the nearest point of the
    box (3-4-5 from a corner), 0 inside; the measure is the product of the extents."""
    r = Region((1.0, 2.0), (4.0, 3.0))
    x = np.array([[1.0, 2.0], [2.5, 2.5], [4.0 + 1e-10, 3.0], [0.0, 2.5], [7.0, 7.0]])
    assert r.contains(x).tolist() == [True, True, True, False, False]
    np.testing.assert_allclose(r.distance(x), [0.0, 0.0, 1e-10, 1.0, 5.0], rtol=1e-12, atol=1e-15)
    assert r.measure == 3.0


def test_graded_axis_halves_towards_the_faces():
    """Uniform nodes h apart plus s +- h 2^-k (k = 1..levels) around each face s, inside
    [0, L], sorted and unique; h must divide L."""
    x = graded_axis(8.0, 1.0, at=(0.0, 3.0), levels=3)
    expected = np.unique(np.r_[np.arange(9.0), 3 + np.array([-0.5, -0.25, -0.125, 0.125, 0.25, 0.5]),
                               [0.125, 0.25, 0.5]])
    np.testing.assert_array_equal(x, expected)
    np.testing.assert_array_equal(graded_axis(4.0, 2.0), [0.0, 2.0, 4.0])
    with pytest.raises(ValueError, match="must divide"):
        graded_axis(5.0, 2.0)


def test_spd_solve_matches_a_dense_solve():
    """bayespd's sparse SPD backend on an assembled-style matrix (duplicate entries summed,
    unsorted COO): the residual is at rounding, 1e-12 relative."""
    rng = np.random.default_rng(3)
    n = 40
    B = sp.random(n, n, density=0.1, random_state=4)
    A = (B @ B.T + n * sp.identity(n)).tocoo()
    dup = sp.coo_matrix((np.r_[A.data / 2, A.data / 2], (np.r_[A.row, A.row], np.r_[A.col, A.col])), A.shape)
    b = rng.standard_normal(n)
    x = spd_solve(dup, b)
    np.testing.assert_allclose(x, np.linalg.solve(A.toarray(), b), rtol=1e-12, atol=1e-14)


def test_bad_input_names_the_fix():
    sup = [Support(Region((0.0, 0.0), (1.0, 2.0)), (0.0, 0.0))]
    load = [BodyLoad(Region((3.0, 0.0), (4.0, 2.0)), (1.0, 0.0))]
    with pytest.raises(ValueError, match="not aligned"):
        solve_box((4.0, 2.0), 1.0, 1.0, 0.3, [Support(Region((0.0, 0.0), (0.5, 2.0)), (0.0, 0.0))], load)
    with pytest.raises(ValueError, match="order 1 or 2"):
        solve_box((4.0, 2.0), 1.0, 1.0, 0.3, sup, load, order=3)
    with pytest.raises(ValueError, match="symmetric 3x3"):
        solve_box((4.0, 2.0), 1.0, 1.0, 0.3, sup, load, stiffness=np.eye(4))
    with pytest.raises(ValueError, match="zero only"):
        solve_box((4.0, 2.0), 1.0, 1.0, 0.3, [Support(sup[0].region, (0.1, 0.0))], load)
    with pytest.raises(ValueError, match="problem is singular"):
        solve_box((4.0, 2.0), 1.0, 1.0, 0.3, [Support(sup[0].region, (None, None))], load)
    fe = solve_box((4.0, 2.0), 1.0, 1.0, 0.3, sup, load, order=1)
    with pytest.raises(ValueError, match="outside the FE box"):
        fe.at([[5.0, 1.0]])


def test_a_large_3d_fe_system_is_solved_by_amg_with_its_rigid_body_modes(monkeypatch):
    """Above the solver crossover (lowered here to 100 dofs) the 3D FE peer's system goes to
    PCG with the AMG V-cycle built on the mesh's 6 rigid-body modes, and agrees with the direct
    factor to 1e-8 relative (kappa * rtol); below it, and for any 2D system, the direct factor
    solves it."""
    from bayespd import linalg
    from bayespd.reference import fem

    calls = []
    monkeypatch.setattr(fem, "v_cycle", lambda A, modes, **kw: calls.append(modes.shape) or v_cycle(A, modes, **kw))

    def solve(dim):
        extent = (8.0, 4.0) if dim == 2 else (4.0, 2.0, 2.0)
        support = [Support(Region((0.0,) * dim, (1.0,) + extent[1:]), (0.0,) * dim)]
        load = [BodyLoad(Region((extent[0] - 1.0,) + (0.0,) * (dim - 1), extent), (0.0,) * (dim - 1) + (-5.0,))]
        return solve_box(extent, 1.0, 1000.0, 0.3, support, load, order=2, plane="stress" if dim == 2 else None).u

    direct = solve(3)
    assert calls == []
    with linalg.settings(direct_max_dofs=100):
        solve(2)
        assert calls == []
        amg = solve(3)
    assert calls and calls[0][1] == 6
    assert np.linalg.norm(amg - direct) <= 1e-8 * np.linalg.norm(direct)
