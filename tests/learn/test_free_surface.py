"""The free-surface-corrected LPS of paper 004 eqs 3.13-3.21 (bayespd.learn.free_surface): patch tests.

Every identity below is exact in the discrete sums (module docstring of free_surface: odd sums over a
point-symmetric family vanish, M_i inverts the intact second moment, the missing set of a straight
edge is mirror-symmetric about its normal), so the tolerances are rounding: 1e-12 of the term scale
(about 40 bonds per node, each term O(scale), float64 eps 2.2e-16: errors of a few 1e-15 seen).
"""
import numpy as np
import pytest
import torch

from bayespd.bonds import find_bonds, precrack
from bayespd.discretize import from_points
from bayespd.influence import Bernstein
from bayespd.learn.free_surface import FreeSurface
from bayespd.learn.kernel import lps_params
from bayespd.materials.lps import LPS

H, DELTA = 5.0, 12.5
LAM, MU = 6.76, 5.40  # eV/A^2, the graphene sheet's (docs/results.md)
PARAMS = lps_params(LAM, MU, [1.0, 2.0, 1.5, 0.5], DELTA)
REACH = DELTA + H / 2  # the bond search radius
NX, NY = 16, 14
CRACK_Y = 6.5 * H      # a pre-crack through the whole width, between rows 6 and 7


def body(crack=None, nx=NX, ny=NY):
    g = np.stack(np.meshgrid(np.arange(nx) * H, np.arange(ny) * H, indexing="ij"), -1).reshape(-1, 2)
    p = from_points(g, np.full(len(g), H * H), h=H)
    bonds = find_bonds(p, DELTA)
    if crack is not None:
        bonds = precrack(p, bonds, crack)
    return p.x, LPS(p, bonds, plane="strain", influence=Bernstein(3))


def uniaxial(axis: int, e: float = 1e-3) -> torch.Tensor:
    """Displacement gradient of the homogeneous strain free of traction on faces normal to the
    other axis (sigma_nn = sigma_np = 0: eps_nn = -lam / (lam + 2 mu) eps_pp), plus a rotation."""
    eps = np.zeros((2, 2))
    eps[axis, axis], eps[1 - axis, 1 - axis] = e, -LAM / (LAM + 2 * MU) * e
    return torch.as_tensor(eps + np.array([[0.0, 4e-4], [-4e-4, 0.0]]))


def stiffness(material) -> torch.Tensor:
    """The project's linearised LPS stiffness K (eq 3.5's operator times V, uncorrected)."""
    pat = material.pattern
    return torch.sparse_coo_tensor(np.stack([pat.rows, pat.cols]), material.numeric_stiffness(PARAMS),
                                   (pat.n, pat.n), check_invariants=True)


SCALE = (LAM + 2 * MU) * 1e-3 / H  # size of one term of L for the strains above


def test_corrected_dilatation_is_exact_for_linear_fields_at_every_node():
    """theta_i = tr H (eqs 3.19-3.20) at corners, edges and crack faces alike."""
    x, material = body([[-1.0, CRACK_Y], [8 * H, CRACK_Y]])
    A = torch.tensor([[1.3e-3, 4e-4], [-2e-4, -7e-4]], dtype=torch.float64)
    theta = FreeSurface(material, PARAMS).dilatation(torch.as_tensor(x) @ A.T + 0.3)
    assert np.abs(theta - 6e-4).max() < 1e-12 * 6e-4


@pytest.mark.parametrize("axis", [0, 1])
def test_traction_free_strain_is_force_free_at_straight_free_edges(axis):
    """L = 0 to rounding at every node whose family touches one straight free edge (the other
    edges are more than the bond reach away); the uncorrected LPS (eq 3.5, m from the bonds
    present) leaves a force of 9 % of the term scale on the edge row, which the correction removes."""
    x, material = body()
    u = torch.as_tensor(x) @ uniaxial(axis).T + torch.tensor([0.1, -0.2], dtype=torch.float64)
    L = FreeSurface(material, PARAMS).operator(u)
    along = x[:, axis]
    away = (along > along.min() + REACH) & (along < along.max() - REACH)
    assert np.abs(L[away]).max() < 1e-12 * SCALE
    across = x[:, 1 - axis]
    edge = away & ((across == across.min()) | (across == across.max()))
    plain = (stiffness(material) @ u.reshape(-1)).reshape(-1, 2) / material.volume[:, None]
    assert float(plain[edge].abs().max(1).values.min()) > 0.05 * SCALE  # 0.094 x SCALE measured


def test_crack_faces_are_free_surfaces_whether_cut_or_broken():
    """A pre-crack through the whole width (bonds removed by ``precrack``) and the same bonds kept
    with gamma = 0 give the same operator; at nodes near the faces and away from the sides a strain
    free of traction on the faces (normal y) gives L = 0."""
    crack = [[-1.0, CRACK_Y], [NX * H, CRACK_Y]]
    x, cut = body(crack)
    _, whole = body()
    b = whole.bonds
    crosses = (np.minimum(x[b.i, 1], x[b.j, 1]) < CRACK_Y) & (np.maximum(x[b.i, 1], x[b.j, 1]) > CRACK_Y)
    assert crosses.sum() == b.n - cut.bonds.n
    u = torch.as_tensor(x) @ uniaxial(0).T
    L_cut = FreeSurface(cut, PARAMS).operator(u)
    L_broken = FreeSurface(whole, PARAMS).operator(u, (~crosses).astype(float))
    assert np.abs(L_cut - L_broken).max() < 1e-13 * SCALE
    away = (x[:, 0] > REACH) & (x[:, 0] < (NX - 1) * H - REACH)
    assert np.abs(L_cut[away]).max() < 1e-12 * SCALE


def test_correction_vanishes_in_the_bulk():
    """Where a node's family and its neighbours' families are complete and intact (two bond
    reaches from every edge), -V L equals the project's linearised LPS force -K u for any u."""
    x, material = body(nx=20, ny=20)
    u = torch.as_tensor(np.random.default_rng(0).normal(size=x.shape) * 1e-2)
    f = FreeSurface(material, PARAMS).force(u)
    plain = -(stiffness(material) @ u.reshape(-1)).reshape(-1, 2)
    bulk = ((x > x.min(0) + 2 * REACH) & (x < x.max(0) - 2 * REACH)).all(1)
    assert bulk.sum() >= 16
    assert torch.allclose(f[bulk], plain[bulk], rtol=0, atol=1e-12 * float(plain.abs().max()))


def test_sites_beyond_prescribed_edges_move_with_their_nearest_node():
    """``free`` rejecting every missing site makes them a collar of the data (eq 3.17's BOmega_D)
    held constant outward: for u depending on y alone the collar sites beyond the left and right
    edges carry the exact linear field, so every node whose family misses only such sites sees a
    complete intact family and L = 0 to rounding; treated as free surface instead, the shear
    u_x = a y is loaded there (sigma_xy != 0 on the side faces) and L does not vanish."""
    x, material = body()
    u = torch.as_tensor(x) @ torch.tensor([[0.0, 1e-3], [0.0, -5e-4]], dtype=torch.float64).T
    L = FreeSurface(material, PARAMS, free=lambda sites: np.zeros(len(sites), bool)).operator(u)
    away = (x[:, 1] > x[:, 1].min() + REACH) & (x[:, 1] < x[:, 1].max() - REACH)
    assert np.abs(L[away]).max() < 1e-12 * SCALE
    side = away & (x[:, 0] == x[:, 0].min())
    assert np.abs(FreeSurface(material, PARAMS).operator(u)[side]).max(1).min() > 0.05 * SCALE


def test_nodes_off_a_square_lattice_are_refused():
    x, material = body()
    moved = x.copy()
    moved[5] += 0.3
    p = from_points(moved, np.full(len(x), H * H), h=H)
    bad = LPS(p, find_bonds(p, DELTA), plane="strain", influence=Bernstein(3))
    with pytest.raises(ValueError, match="square lattice"):
        FreeSurface(bad, PARAMS)
