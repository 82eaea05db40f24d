"""PD against a finite-element peer (issue 3): the FE reference, the lattice tensor C_m, and
the convergence of LPS to FE on seed 001's beam (2D) and a cantilever (3D).

Bounds are measured values with a margin (numbers in comments); rates come from theory:
nonlocal Dirichlet layers and truncated families near free surfaces give O(delta) errors.
"""
import numpy as np
import pytest

import bayespd as bp

pytest.importorskip("skfem")

from bayespd.reference import (cantilever, isotropic_stiffness, lattice_stiffness,  # noqa: E402
                               observed_order, pd_versus_fe, relative_l2, solve_box,
                               three_point_bending as beam)
from bayespd.reference.fem import BodyLoad, Region, Support  # noqa: E402

MARGIN = 4.0


@pytest.fixture(scope="module")
def beam_points():
    g = bp.grid_2d(beam.LENGTH, beam.WIDTH, 1.0)
    return g.x[beam.away_mask(g.x, MARGIN)]


@pytest.fixture(scope="module")
def beam_fe():
    """Graded Q2 peers of the beam at h = 2 and 1 mm (71k dofs; 1e-5 from h = 0.5)."""
    return {h: beam.fe_solution(h) for h in (2.0, 1.0)}


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


def test_fe_reference_converges_with_grading(beam_fe, beam_points):
    """The fixed patches' corners are stress singularities: on a uniform mesh they pollute
    the whole field (measured 4.8e-3 at h = 2 against the graded h = 1 peer); geometric
    grading toward them brings Q2 to changes below 1e-4 (measured 2.9e-5 from h = 2 to 1,
    1.2e-5 from h = 1 to 0.5: the experiment's reference)."""
    ref = beam_fe[1.0].at(beam_points)
    graded = relative_l2(beam_fe[2.0].at(beam_points), ref)
    uniform = relative_l2(beam.fe_solution(2.0, grading=0).at(beam_points), ref)
    assert graded < 1e-4
    assert uniform > 50 * graded  # measured 160x


def test_pd_beam_error_bounded_and_decreasing(beam_fe):
    """LPS plane stress, m = 3, against the isotropic FE beam (measured 0.0593 at h = 2 and
    0.0172 at h = 1: halving delta divides the error by 3.4, at least first order)."""
    e = {h: pd_versus_fe(beam, h, 3, {"iso": beam_fe[1.0]}, MARGIN)["errors"]["iso"]
         for h in (2.0, 1.0)}
    assert e[2.0] < 0.066
    assert e[1.0] < 0.019
    assert e[2.0] / e[1.0] > 2.0


def test_lattice_stiffness_exact_on_average():
    """Dilatation is exact on the grid and the rotational average of the deviatoric energy is
    exact, so C_m is isotropic 'on average'; its cubic anisotropy (1.9e-2 at m = 3) fades as m
    grows (2.6e-5 at m = 16)."""
    K, G = (float(v) for v in bp.moduli_from_young(4000.0, 0.3))
    kappa = 9 * K * G / (3 * K + 4 * G)  # plane-stress in-plane bulk modulus
    C = lattice_stiffness(3, K, G, dim=2)
    np.testing.assert_allclose(C[0, 0] + C[0, 1], 2 * kappa, rtol=1e-10)
    np.testing.assert_allclose((C[0, 0] - C[0, 1]) / 2 + C[2, 2], 2 * G, rtol=1e-10)
    assert C[0, 2] == 0 and C[1, 2] == 0
    C3 = lattice_stiffness(2, K, G, dim=3)
    np.testing.assert_allclose(C3[0, 0] + 2 * C3[0, 1], 3 * K, rtol=1e-10)
    np.testing.assert_allclose((C3[0, 0] - C3[0, 1] + 3 * C3[3, 3]) / 5, G, rtol=1e-10)
    iso = isotropic_stiffness(4000.0, 0.3, 2)
    a3, a16 = (np.linalg.norm(lattice_stiffness(m, K, G) - iso) / np.linalg.norm(iso) for m in (3, 16))
    assert 0.01 < a3 < 0.03 and a16 < a3 / 100


@pytest.mark.slow
def test_beam_first_order_in_delta_at_fixed_m():
    """m = 3, h = 2, 1, 0.5 mm. Against the FE peer with the lattice tensor C_3 (the fixed-m
    limit) the error is O(delta): measured least-squares order 1.29 (steps 1.62, 0.95);
    theory 1, so 0.8 to 1.6. Against the isotropic FE it is 1.1 % at h = 0.5 (DIC
    resolution; target 3 %), where the lattice anisotropy floor (about 1 %) takes over."""
    K, G = beam.params(1.0)["K"], beam.params(1.0)["G"]
    refs = {"iso": beam.fe_solution(0.5), "lattice": beam.fe_solution(0.5, stiffness=lattice_stiffness(3, K, G))}
    rows = [pd_versus_fe(beam, h, 3, refs, MARGIN) for h in (2.0, 1.0, 0.5)]
    p = observed_order([r["delta"] for r in rows], [r["errors"]["lattice"] for r in rows])
    assert 0.8 < p < 1.6
    assert rows[-1]["errors"]["iso"] < 0.015
    assert rows[-1]["errors"]["lattice"] < 0.013  # measured 0.0110


@pytest.mark.slow
def test_cantilever_3d_converges():
    """3D LPS, m = 2, h = 1 and 2/3 mm, against the graded Q2 hex peer (about 2 min).

    The FE peer changes by 8.7e-5 from 3 to 4 grading levels. Surface-corrected LPS against
    the lattice peer (the limit at fixed m): errors 0.073 and 0.036, order 1.8 (theory: at
    least 1); against the isotropic peer 0.028 and 0.017 (floor: the 2.7 % lattice
    anisotropy at m = 2). Plain LPS is stiffer along free surfaces (an O(delta) term with a
    large constant in a slender section): against the lattice peer 0.096 and 0.087,
    decreasing but pre-asymptotic at these delta / depth."""
    K, G = cantilever.params(1.0)["K"], cantilever.params(1.0)["G"]
    g = bp.grid_3d(cantilever.LENGTH, cantilever.WIDTH, cantilever.DEPTH, 2 / 3)
    points = g.x[cantilever.away_mask(g.x, MARGIN)]
    iso = cantilever.fe_solution(grading=4)
    coarse = cantilever.fe_solution(grading=3)
    assert relative_l2(coarse.at(points), iso.at(points)) < 1e-4
    lattice = cantilever.fe_solution(grading=3, stiffness=lattice_stiffness(2, K, G, dim=3))
    refs = {"iso": iso, "lattice": lattice}
    corrected = [pd_versus_fe(cantilever, h, 2, refs, MARGIN, surface_correction=True) for h in (1.0, 2 / 3)]
    p = observed_order([r["delta"] for r in corrected], [r["errors"]["lattice"] for r in corrected])
    assert p > 1.0
    assert corrected[-1]["errors"]["lattice"] < 0.045 and corrected[-1]["errors"]["iso"] < 0.025
    plain = [pd_versus_fe(cantilever, h, 2, refs, MARGIN)["errors"]["lattice"] for h in (1.0, 2 / 3)]
    assert plain[1] < plain[0] < 0.11
