"""WENO coarse graining (paper 004 eqs 2.1-2.12): exact on affine fields at the coarse-grained
position, within the Taylor bound on smooth ones, mass-conserving, and far less smeared than the
plain cone average next to a displacement jump."""
import numpy as np
import pytest

from bayespd.learn.coarse_grain import coarse_grain, smoothness

H = 5.0


def _cloud(rng, size=40.0, spacing=1.0):
    g = np.arange(spacing / 2, size, spacing)
    X = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    return X + rng.uniform(-0.2, 0.2, X.shape) * spacing


def _nodes(size=40.0):
    g = np.arange(H / 2, size, H)
    return np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)


@pytest.mark.parametrize("weno", [False, True])
def test_affine_field_is_reproduced_exactly_at_the_coarse_position(rng, weno):
    X = _cloud(rng)
    M = rng.uniform(10.0, 14.0, len(X))
    A, c = np.array([[0.01, -0.02], [0.015, 0.005]]), np.array([0.3, -0.1])
    U = (X @ A.T + c)[None]
    cg = coarse_grain(_nodes(), X, M, U, np.zeros_like(U), 2 * H, H * H, weno=weno, band=0.75)
    np.testing.assert_allclose(cg.u[0], cg.x[0] @ A.T + c, atol=1e-13)
    assert np.abs(cg.x[0] - cg.nodes).max() < H  # a weighted centroid stays within the cone


def test_smooth_field_error_is_within_the_taylor_bound(rng):
    X = _cloud(rng)
    k = 2 * np.pi / 40.0
    U = 0.05 * np.stack([np.sin(k * X[:, 0]) * np.cos(k * X[:, 1]), np.cos(k * X[:, 0])], 1)[None]
    for weno in (False, True):
        cg = coarse_grain(_nodes(), X, np.ones(len(X)), U, np.zeros_like(U), 2 * H, H * H, weno=weno, band=0.75)
        x = cg.x[0]
        exact = 0.05 * np.stack([np.sin(k * x[:, 0]) * np.cos(k * x[:, 1]), np.cos(k * x[:, 0])], 1)
        bound = 0.5 * (0.05 * 2 * k**2) * (2 * H) ** 2  # 1/2 |Hessian| R^2, |Hessian| <= 2 k^2 amplitude
        assert np.abs(cg.u[0] - exact).max() <= bound


def test_mass_and_force_are_conserved_and_periodic_images_agree(rng):
    box = np.array([40.0, 40.0])
    X = _cloud(rng)
    M = rng.uniform(10.0, 14.0, len(X))
    B = rng.normal(size=(1, len(X), 2))
    U = 0.01 * np.stack([np.sin(2 * np.pi * X[:, 1] / 40.0), np.zeros(len(X))], 1)[None]
    cg = coarse_grain(_nodes(), X, M, U, B, 2 * H, H * H, box=box, band=0.75)
    np.testing.assert_allclose(cg.rho[0].sum() * H * H, M.sum(), rtol=1e-12)
    np.testing.assert_allclose(cg.b[0].sum(0) * H * H, B[0].sum(0), atol=1e-10)
    shifted = coarse_grain(_nodes(), X + box, M, U, B, 2 * H, H * H, box=box, band=0.75)
    np.testing.assert_allclose(shifted.u, cg.u, atol=1e-14)


def _jump(rng, J=1.0):
    X = _cloud(rng)
    smooth = lambda x: 0.01 * np.stack([np.sin(x[:, 1] / 7), np.cos(x[:, 0] / 9)], 1)
    side = np.sign(X[:, 0] - 20.0)
    U = (smooth(X) + 0.5 * J * side[:, None] * np.array([1.0, 0.0]))[None]
    return X, U, smooth


def test_weno_does_not_smear_across_a_crack(rng):
    """Fig. 1's point, measured: a straight opening jump J at x = 20, nodes 2.5 and 7.5 from it;
    the WENO average's RMS error there is at least 4x below the plain average's (measured 6x)."""
    X, U, smooth = _jump(rng)
    nodes = _nodes()
    near = np.abs(nodes[:, 0] - 20.0) < 2 * H
    errors = {}
    for weno in (False, True):
        cg = coarse_grain(nodes, X, np.ones(len(X)), U, np.zeros_like(U), 2 * H, H * H, weno=weno, band=0.75)
        ref = smooth(cg.x[0]) + 0.5 * np.sign(nodes[:, 0] - 20.0)[:, None] * np.array([1.0, 0.0])
        err = np.linalg.norm(cg.u[0] - ref, axis=1)
        errors[weno] = np.sqrt((err[near] ** 2).mean())
        assert err[~near].max() < 0.01 * 0.5 * (2 * H) ** 2 / 49  # away from the jump: the smooth bound
    assert errors[False] > 0.15  # the plain average mixes the faces: a sizeable fraction of J
    assert errors[True] < errors[False] / 4


def test_indicator_is_small_across_the_jump_and_near_one_along_a_smooth_field(rng):
    X, U, _ = _jump(rng)
    node = np.array([17.5, 17.5])
    v = X[np.linalg.norm(X - node, axis=1) < 2 * H] - node
    U0 = U[0][np.linalg.norm(X - node, axis=1) < 2 * H]
    alpha = smoothness(v, U0, band=0.75)
    across = node[0] + v[:, 0] > 20.5
    assert np.median(alpha[across]) < 1e-3
    assert np.median(alpha[~across]) > 0.5
    flat = smoothness(v, np.zeros_like(U0), band=0.75)  # below the resolution: smooth
    np.testing.assert_allclose(flat, 1.0)


def test_bad_input_is_refused_with_the_fix(rng):
    X, U, _ = _jump(rng)
    far = np.array([[500.0, 500.0]])
    with pytest.raises(ValueError, match="raise radius or keep the nodes inside"):
        coarse_grain(far, X, np.ones(len(X)), U, np.zeros_like(U), 2 * H, H * H)
    with pytest.raises(ValueError, match=r"U and B must be \(frames"):
        coarse_grain(_nodes(), X, np.ones(len(X)), U[0], np.zeros_like(U[0]), 2 * H, H * H)
    bad = U.copy()
    bad[0, 3, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        coarse_grain(_nodes(), X, np.ones(len(X)), bad, np.zeros_like(U), 2 * H, H * H)
