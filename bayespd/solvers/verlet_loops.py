"""Velocity Verlet's update and energy bookkeeping as compiled loops over the dofs
(``bond_loops``' numba, optional), for ``dynamics.velocity_verlet`` on the CPU without a
gradient to record.

torch runs each of the update's ~15 element-wise operations and two reductions on its
OpenMP pool; with two threads on a shared two-core machine every one of them waits at a
barrier for a worker the scheduler has put aside, and a 100k-particle step took 10x its force
(benchmarks/README.md, "The explicit step on two threads"). Here one pass a step does the kick
of step n, its energy sums and the drift of step n + 1 (``kick``), on ``torch.get_num_threads()``
threads in runs of CHUNK dofs claimed as the force's bond shares are (``bond_loops.claimed``),
and writes no temporaries. The loops do torch's element-wise operations in its order, so in
float64 the trajectory is the same to the last bit; the energies are sums of per-run partial
sums in run order (the same bits for any thread count), within n eps sum |terms| of torch's
(tests/solvers/test_verlet_loops.py).
"""
from __future__ import annotations

import numpy as np
import torch

from bayespd import bond_loops

CHUNK = 1 << 15  # dofs per run of the update, whatever the thread count (the energies' bits)


def usable(*tensors) -> bool:
    """True when the loops can stand in for torch (``bond_loops.usable``)."""
    return bond_loops.usable(*tensors)


def drift(u: torch.Tensor, v: torch.Tensor, f: torch.Tensor, m: torch.Tensor, dt: float, damping: float):
    """(v_half, u_new) = (v + dt/2 (f/m - damping v), u + dt v_half): the first step's drift."""
    v_half, u_new = torch.empty_like(v), torch.empty_like(u)
    _kick_drift(*_arrays(v, f, m), dt, damping, *_arrays(f, u, u), False, True, 0, len(u),
                *_arrays(v, v_half, u_new))
    return v_half, u_new


def kick(v_half, f_new, m, dt: float, damping: float, f, u_new, u, then_drift: bool = True):
    """(v, work, kinetic, (v_half', u_new')): v = (v_half + dt/2 f_new/m) / (1 + dt/2 damping),
    the trapezoidal work 1/2 (f + f_new) . (u_new - u) and 1/2 m v . v, and (``then_drift``)
    the next step's drift from (u_new, v, f_new), else None."""
    v = torch.empty_like(v_half)
    nxt = (torch.empty_like(v), torch.empty_like(u_new)) if then_drift else (v, v)
    args = (*_arrays(v_half, f_new, m), dt, damping, *_arrays(f, u_new, u), True, then_drift)
    outs = _arrays(v, *nxt)
    n = len(u)
    cuts = list(range(0, n, CHUNK)) + [n]

    def run(t):
        return _kick_drift(*args, cuts[t], cuts[t + 1], *outs)

    sums = bond_loops.claimed(run, len(cuts) - 1, torch.get_num_threads())
    work, kinetic = 0.0, 0.0
    for w, k in sums:
        work, kinetic = work + w, kinetic + k
    return v, 0.5 * work, 0.5 * kinetic, nxt if then_drift else None


def _arrays(*tensors):
    return [t.detach().numpy() for t in tensors]


@bond_loops.cached_kernel
def _kick_drift(v_half, f_new, m, dt, damping, f, u_new, u, kick, then_drift, a0, a1, v, v_next, u_next):  # pragma: no cover
    """On dofs [a0, a1): v from the half step (``kick``; else v = v_half), the sums of
    (f + f_new)(u_new - u) and m v v, then (``then_drift``) v_next = v + dt/2 (f_new/m -
    damping v), u_next = u_new + dt v_next."""
    work, kinetic = 0.0, 0.0
    shrink = 1 + 0.5 * damping * dt  # 1 without damping: x / 1 = x, a division saved
    for a in range(a0, a1):
        if kick:
            va = v_half[a] + 0.5 * dt * f_new[a] / m[a]
            if shrink != 1.0:
                va = va / shrink
            v[a] = va
            work += (f[a] + f_new[a]) * (u_new[a] - u[a])
            kinetic += m[a] * va * va
        else:
            va = v_half[a]
        if then_drift:
            vn = va + 0.5 * dt * (f_new[a] / m[a] - damping * va)
            v_next[a] = vn
            u_next[a] = u_new[a] + dt * vn
    return work, kinetic
