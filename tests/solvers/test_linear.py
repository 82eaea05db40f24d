"""``bayespd.solvers.linear``: the linearised force f(u) = p - A u with A = K + eps I (Dodwell
2019 eq 3), with and without constraints, its equilibrium A^-1 p and its refusal when a piece
floats and eps = 0, the Lanczos largest eigenvalue, and the finite-difference Hessian operator
(exact for a linear force up to rounding / h)."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch

import bayespd as bp
from bayespd.solvers import LinearForce, largest_eigenvalue, linear_elastic
from bayespd.solvers.linear import as_matvec, hessian_operator
from tests.conftest import plate_scene

PARAMS = {"K": 3.0, "G": 2.0, "delta": 2.5}


@pytest.fixture(scope="module")
def scene():
    return plate_scene()


def random(n, seed, *shape):
    return torch.randn(n, *shape, generator=torch.Generator().manual_seed(seed))


def test_unconstrained_force_is_p_minus_K_plus_eps_u(scene):
    """A = K + eps I (all N*dim dofs), symmetric; f(u) = p - A u column by column; V(u) =
    u^T A u / 2 - p^T u; the equilibrium solves A u = p to 1e-12 relative residual."""
    mat, eps = scene.material, 0.1
    load = random(scene.particles.n, 0, 2)
    F = linear_elastic(mat, PARAMS, load=load, eps=eps)
    A = mat.pattern.matrix(mat.numeric_stiffness(PARAMS)).toarray() + eps * np.eye(mat.pattern.n)
    assert np.abs(F.matrix.toarray() - A).max() == 0.0
    assert abs(F.matrix - F.matrix.T).max() <= 1e-15 * np.abs(A).max()  # symmetric to rounding
    p = load.reshape(-1).numpy()
    U = random(F.n, 1, 3)
    np.testing.assert_allclose(F(U).numpy(), p[:, None] - A @ U.numpy(), rtol=0, atol=1e-12 * np.abs(A).max())
    np.testing.assert_allclose(F.energy(U).numpy(), np.einsum("ib,ib->b", U.numpy(), 0.5 * A @ U.numpy() - p[:, None]),
                               rtol=1e-12)
    u = F.equilibrium().numpy()
    assert np.linalg.norm(A @ u - p) <= 1e-12 * np.linalg.norm(A, 2) * np.linalg.norm(u)
    assert len(F.floating) == 0


@pytest.mark.parametrize("value", [(0.0, 0.0), (0.05, -0.02)])
def test_constrained_equilibrium_is_the_static_solve(scene, value):
    """With constraints the state is the free dofs, A = K_ff and the prescribed displacements
    enter the load as -K_fc u_c: A^-1 p equals the free dofs of ``Scene.solve`` to 1e-10."""
    p = scene.particles
    bcs = [*scene.dirichlet, bp.Dirichlet.layer(p, "right", 2.5, value)]
    sc = bp.Scene(scene.material, bcs, [bp.Load(p.layer("top", 1.0), (0.0, 5.0))])
    F = linear_elastic(sc.material, PARAMS, load=sc.force, constraints=sc.constraints)
    c = sc.constraints
    assert F.n == len(c.free_dofs)
    K = sc.material.pattern.matrix(sc.material.numeric_stiffness(PARAMS)).toarray()
    np.testing.assert_array_equal(F.matrix.toarray(), K[np.ix_(c.free_dofs, c.free_dofs)])
    u = sc.solve(PARAMS).detach()
    np.testing.assert_allclose(F.equilibrium().numpy(), c.free(u).numpy(), rtol=0,
                               atol=1e-10 * float(u.abs().max()))
    assert float(F(c.free(u)).abs().max()) <= 1e-10 * float(F.load.abs().max())


def broken_particle(mat, k):
    intact = torch.ones(mat.bonds.n)
    intact[torch.as_tensor((mat.bonds.i == k) | (mat.bonds.j == k))] = 0.0
    return intact


def test_a_floating_particle_is_refused_naming_eps(scene):
    """eps = 0 with particle k cut loose: A is singular and equilibrium refuses, naming the
    particle and the fix; with eps > 0 the equilibrium exists and k (unloaded) stays at 0."""
    mat = scene.material
    k = int(np.flatnonzero(scene.particles.box([4, 2], [5, 3]))[0])
    intact = broken_particle(mat, k)
    F0 = linear_elastic(mat, PARAMS, scene.force, eps=0.0, constraints=scene.constraints, intact=intact)
    assert list(F0.floating) == [k]
    with pytest.raises(bp.NotPositiveDefiniteError, match=rf"particle {k}\).*Pass eps > 0 to linear_elastic"):
        F0.equilibrium()
    F = linear_elastic(mat, PARAMS, scene.force, eps=1e-6, constraints=scene.constraints, intact=intact)
    assert len(F.floating) == 0
    u = scene.constraints.embed(F.equilibrium())
    assert float(u[k].abs().max()) == 0.0 and float(u.abs().max()) > 0


def test_bad_eps_and_load_shapes_are_refused(scene):
    with pytest.raises(ValueError, match="eps must be >= 0"):
        linear_elastic(scene.material, PARAMS, eps=-1.0)
    with pytest.raises(ValueError, match="nodal forces"):
        linear_elastic(scene.material, PARAMS, load=torch.ones(3))
    with pytest.raises(ValueError, match="load must have 4 entries"):
        LinearForce(sp.identity(4), torch.ones(3))


def test_largest_eigenvalue_is_lanczos_to_the_dense_value(scene):
    F = linear_elastic(scene.material, PARAMS, eps=0.0, constraints=scene.constraints)
    dense = np.linalg.eigvalsh(F.matrix.toarray())[-1]
    for op in (F.matrix, lambda v: F.matrix @ v):
        lam = largest_eigenvalue(as_matvec(op), F.n)
        assert abs(lam - dense) <= 1e-8 * dense
    assert largest_eigenvalue(as_matvec(sp.identity(1) * 7.5), 1) == 7.5


def test_hessian_operator_of_a_linear_force_is_its_matrix(scene):
    """(f(u) - f(u + h v)) / h = A v exactly in exact arithmetic; in float64 the rounding of
    f over h = eps^(3/8) leaves a relative error ~ 1e-16 / 1.3e-6 ~ 1e-10."""
    F = linear_elastic(scene.material, PARAMS, load=scene.force, constraints=scene.constraints)
    u = random(F.n, 2)
    H = hessian_operator(F, u)
    for seed in (3, 4):
        v = random(F.n, seed).numpy()
        Av = F.matrix @ v
        assert np.abs(H(v) - Av).max() <= 1e-8 * np.abs(Av).max()
