"""bayespd/solvers/verlet_loops.py: velocity Verlet with the compiled update against the
torch update, on the same force (a fixed sparse matvec, so only the update differs)."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.solvers import linear_elastic, lumped_mass, velocity_verlet, verlet_loops

pytest.importorskip("numba")


def run(dtype, compiled, monkeypatch, damping):
    """50 damped Verlet steps of a 12 x 8 PMB plate from a bump, the update compiled or not."""
    p = bp.grid_2d(12, 8, 1.0)
    A = linear_elastic(bp.BondBased(p, bp.find_bonds(p, 3.0)), {"K": 1.0, "delta": 3.0}).matrix.tocsr()
    A = A.astype(np.float32 if dtype == torch.float32 else np.float64)
    M = lumped_mass(p, 1.0 + p.x[:, 0] / 12).to(dtype)
    u0 = torch.as_tensor(0.01 * np.exp(-((p.x - p.x.mean(0)) ** 2).sum(1) / 4)).repeat_interleave(2).to(dtype)
    monkeypatch.setattr(verlet_loops, "usable", verlet_loops.usable if compiled else (lambda *t: False))
    return velocity_verlet(lambda u: torch.from_numpy(-(A @ u.numpy())), M, u0, 0.2, 50, damping=damping, save_every=10)


@pytest.fixture
def threads():
    """Sets torch's thread count for a test, restoring it afterwards."""
    before = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(before)


@pytest.mark.parametrize("runs", [(1 << 15, 1), (37, 3)])
@pytest.mark.parametrize("damping", [0.0, 0.3])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_update_is_the_torch_update(dtype, damping, runs, threads, monkeypatch):
    """The loops do torch's element-wise operations in its order, in one run of all 192 dofs
    on one thread or in runs of 37 claimed by 3 threads (each step's kick fused with the next
    drift): in float64 the states and velocities are equal bit for bit; float32 to a few ulp
    per step (torch may round its scalar factors to float32 first; 50 steps, 1e-5 relative).
    The energies are sums in another order, each off by at most n eps/2 sum |terms| (n = 192
    terms): to 1e-12 relative (float64) and 1e-5 (float32) of the largest."""
    monkeypatch.setattr(verlet_loops, "CHUNK", runs[0])
    threads(runs[1])
    got, ref = (run(dtype, compiled, monkeypatch, damping) for compiled in (True, False))
    assert got.final.dtype == got.u.dtype == dtype
    if dtype == torch.float64:
        assert torch.equal(got.u, ref.u) and torch.equal(got.v, ref.v) and torch.equal(got.final_v, ref.final_v)
    else:
        scale = float(ref.u.abs().max())
        assert float((got.u - ref.u).abs().max()) <= 1e-5 * scale
        assert float((got.v - ref.v).abs().max()) <= 1e-5 * float(ref.v.abs().max())
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for a, b in ((got.kinetic, ref.kinetic), (got.potential, ref.potential)):
        np.testing.assert_allclose(a, b, rtol=0, atol=tol * np.abs(b).max())


def test_a_force_with_a_gradient_keeps_the_torch_update():
    """Where the loops cannot stand in (a tensor that records a gradient), the torch update
    runs and the gradient reaches the initial state."""
    M = torch.ones(4, dtype=torch.float64)
    u0 = torch.tensor([0.1, 0.0, -0.1, 0.2], dtype=torch.float64, requires_grad=True)
    out = velocity_verlet(lambda u: -2.0 * u, M, u0, 0.1, 5)
    out.final.sum().backward()
    c = float(torch.cos(torch.tensor(np.sqrt(2.0) * 0.5)))
    assert abs(float(u0.grad[0]) - c) < 1e-2  # u(t) = u0 cos(sqrt(2) t), Verlet to O(dt^2)
