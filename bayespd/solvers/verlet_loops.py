"""Velocity Verlet's update and energy bookkeeping as two compiled loops over the dofs
(``bond_loops``' numba, optional), for ``dynamics.velocity_verlet`` on the CPU without a
gradient to record.

torch runs each of the update's ~15 element-wise operations and two reductions on its
OpenMP pool; with two threads on a shared two-core machine every one of them waits at a
barrier for a worker the scheduler has put aside, and a 100k-particle step took 10x its force
(benchmarks/README.md, "The explicit step on two threads"). These loops run on the calling
thread and write no temporaries; they do torch's operations in its order, so in float64 the
trajectory is the same to the last bit and the energies agree to the rounding of their sums
(tests/solvers/test_verlet_loops.py).
"""
from __future__ import annotations

import numpy as np
import torch

from bayespd import bond_loops


def usable(*tensors) -> bool:
    """True when the loops can stand in for torch (``bond_loops.usable``)."""
    return bond_loops.usable(*tensors)


def drift(u: torch.Tensor, v: torch.Tensor, f: torch.Tensor, m: torch.Tensor, dt: float, damping: float):
    """(v_half, u_new) = (v + dt/2 (f/m - damping v), u + dt v_half)."""
    v_half, u_new = torch.empty_like(v), torch.empty_like(u)
    _drift(*_arrays(u, v, f, m), dt, damping, v_half.numpy(), u_new.numpy())
    return v_half, u_new


def kick(v_half, f_new, m, dt: float, damping: float, f, u_new, u):
    """(v, work, kinetic): v = (v_half + dt/2 f_new/m) / (1 + dt/2 damping), the trapezoidal
    work 1/2 (f + f_new) . (u_new - u) and 1/2 m v . v, sums in dof order."""
    v = torch.empty_like(v_half)
    work, kinetic = _kick(*_arrays(v_half, f_new, m), dt, damping, *_arrays(f, u_new, u), v.numpy())
    return v, float(work), float(kinetic)


def _arrays(*tensors):
    return [t.detach().numpy() for t in tensors]


@bond_loops.cached_kernel
def _drift(u, v, f, m, dt, damping, v_half, u_new):  # pragma: no cover (compiled)
    for a in range(u.shape[0]):
        v_half[a] = v[a] + 0.5 * dt * (f[a] / m[a] - damping * v[a])
        u_new[a] = u[a] + dt * v_half[a]


@bond_loops.cached_kernel
def _kick(v_half, f_new, m, dt, damping, f, u_new, u, v):  # pragma: no cover (compiled)
    work, kinetic = 0.0, 0.0
    for a in range(u.shape[0]):
        v[a] = (v_half[a] + 0.5 * dt * f_new[a] / m[a]) / (1 + 0.5 * damping * dt)
        work += (f[a] + f_new[a]) * (u_new[a] - u[a])
        kinetic += m[a] * v[a] * v[a]
    return 0.5 * work, 0.5 * kinetic
