"""The symmetry plane: the half-model reproduces the full model on the kept half to solver
tolerance; a normal-component layer or column at the plane does not."""
import numpy as np
import pytest
import torch

import bayespd as bp

H, DELTA = 1.0, 3.0
PARAMS = {"K": 2000.0, "G": 900.0, "delta": 2.6}


def _scene(p, material, load_scale):
    """Clamped at the bottom, pulled up on top and outwards on both sides (mirror-symmetric)."""
    loads = [bp.Load(p.layer("top", H), (0.0, 40.0 * load_scale)),
             bp.Load(p.layer("right", H) & ~p.layer("bottom", DELTA), (25.0, 0.0))]
    if load_scale == 1.0:
        loads.append(bp.Load(p.layer("left", H) & ~p.layer("bottom", DELTA), (-25.0, 0.0)))
    return bp.Scene(material, [bp.Dirichlet.layer(p, "bottom", DELTA)], loads)


@pytest.fixture(scope="module")
def full():
    p = bp.grid_2d(16.0, 8.0, H)
    u = _scene(p, bp.LPS(p, bp.find_bonds(p, DELTA)), 1.0).solve(PARAMS)
    right = p.x[:, 0] > 8.0
    return p.x[right], u[right]


def test_half_model_reproduces_the_full_model(full):
    x, u_full = full
    half = bp.grid_2d(8.0, 8.0, H, origin=(8.0, 0.0))
    plane = bp.SymmetryPlane(half, axis=0, at=8.0, delta_max=DELTA)
    folded = plane.fold(bp.LPS(plane.extended, bp.find_bonds(plane.extended, DELTA)))
    scene = _scene(half, folded, 0.5)
    K = scene.constraints.pattern.matrix(scene.stiffness_values(PARAMS))
    assert abs(K - K.T).max() < 1e-12 * abs(K).max()  # S K E is symmetric (module docstring)
    u = scene.solve(PARAMS)
    assert np.array_equal(half.x, x)
    assert float((u - u_full).abs().max()) < 1e-10 * float(u_full.abs().max())
    # differentiable like any scene: the adjoint gradient matches the full model's
    K_t = torch.tensor(2000.0, requires_grad=True)
    scene.solve({**PARAMS, "K": K_t})[:, 1].sum().backward()
    assert torch.isfinite(K_t.grad) and float(K_t.grad) < 0


@pytest.mark.parametrize("depth", [DELTA, H])
def test_a_normal_component_layer_or_column_biases_the_half(full, depth):
    """u_x = 0 on a layer one horizon thick forces u_x = 0 where the full body moves; one
    column leaves the particles beside it with half a family: both miss by far more than 1 %."""
    x, u_full = full
    half = bp.grid_2d(8.0, 8.0, H, origin=(8.0, 0.0))
    scene = _scene(half, bp.LPS(half, bp.find_bonds(half, DELTA)), 0.5)
    roller = bp.roller(half, half.layer("left", depth), axis=0)
    scene = bp.Scene(scene.material, scene.dirichlet + [roller], scene.loads)
    u = scene.solve(PARAMS)
    assert float((u - u_full).abs().max()) > 0.05 * float(u_full.abs().max())


def test_refuses_particles_on_or_across_the_plane():
    p = bp.grid_2d(4.0, 4.0, 1.0)
    with pytest.raises(ValueError, match="strictly on one side of the plane"):
        bp.SymmetryPlane(p, axis=0, at=2.0, delta_max=2.0)
    with pytest.raises(ValueError, match="strictly on one side of the plane"):
        bp.SymmetryPlane(p, axis=1, at=0.5, delta_max=2.0)
    with pytest.raises(ValueError, match="axis must be < 2"):
        bp.SymmetryPlane(p, axis=2, at=0.0, delta_max=2.0)
    plane = bp.SymmetryPlane(p, axis=0, at=0.0, delta_max=2.0)
    with pytest.raises(ValueError, match="build the material on plane.extended"):
        plane.fold(bp.LPS(p, bp.find_bonds(p, 2.0)))
    with pytest.raises(ValueError, match="delta_max=3 > the plane's delta_max=2"):
        plane.fold(bp.LPS(plane.extended, bp.find_bonds(plane.extended, 3.0)))
