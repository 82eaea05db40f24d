"""Dynamic PD forward run of a coarse-grained MD record (paper 004 sec. 5.2-5.3, eqs 3.5-3.10):
the learned LPS surrogate with the smoothed damage law integrated in time on the coarse grid.

    m_i u_i'' = f_i(u; gamma) + V_i b_i(t),   m_i = rho_i V_i,

f the project's exact-kinematics LPS force (``bayespd.nonlinear``, ``materials/lps.py``: a bond
of intact fraction gamma keeps gamma w of its weight and the weighted volume m is recomputed from
the intact bonds), gamma_b = (1 - tanh((max_t s_b - s0) / eta)) / 2 (eq 3.10, irreversible,
``bayespd.damage.SmoothStep``), eta a fixed share of s0 (``eta_over_s0``; the paper tunes it by
hand). Velocity Verlet: drift, prescribed nodes set to their displacement at the new time,
damage update with the new stretch, force, kick. The prescribed nodes follow ``moving(t)`` (e.g.
the coarse-grained MD displacement of the pulled edge columns, linear in time between frames);
the free nodes start from ``v0``. The step is ``safety`` times the Verlet limit
2 / sqrt(lambda_max(M^-1 K)) of the intact linearised operator (damage only softens it).
``surface``: f_i = -V_i L_i with L the free-surface-corrected LPS of paper 004 eq 3.18
(``bayespd.learn.free_surface``: linear in u for given gamma, missing bonds as broken ones) in
place of the exact-kinematics force.

Units: A, ps, rho in g/mol per A^2 (times ``MASS``), b in eV/A^3.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse
import torch

from bayespd import bond_loops
from bayespd.damage import DamageIndex, SmoothStep
from bayespd.learn.free_surface import FreeSurface
from bayespd.nonlinear import NonlinearBonds
from bayespd.solvers.dynamics import NumericalInstabilityError, stable_time_step
from bayespd.validate import positive

MASS = 1.0 / 9648.533212  # eV ps^2 / A^2 per g/mol (1 g/mol = 1.0364e-4 eV ps^2 / A^2)
ETA_OVER_S0 = 0.25  # eq 3.10's default width eta = s0 / 4: gamma(0) = 0.9997 at any s0 (a fixed eta = 0.05
#                     weakens every bond at the small s0 a search visits: gamma(0) = 0.69 at s0 = 0.01)


@dataclass
class ForwardRun:
    """Saved at ``t`` (the requested frame times): ``u`` (F, N, 2), damage index ``phi`` (F, N)
    (``bayespd.damage.DamageIndex`` with the kernel's weights), bond intact fractions ``intact``
    (F, bonds), ``energy`` (F,) kinetic + strain
    energy of the free nodes' motion (eV; conserved when nothing breaks and nothing is
    prescribed; None for a run of a batch, ``forward_runs``), the step ``dt``, the number of steps
    and the wall time (a batch's shared equally)."""
    t: np.ndarray
    u: np.ndarray
    phi: np.ndarray
    intact: np.ndarray
    energy: np.ndarray | None
    dt: float
    steps: int
    wall_time_s: float


def linear_in_time(times, values) -> Callable[[float], np.ndarray]:
    """t -> values interpolated linearly between ``times`` (F,) (values (F, ...)); held beyond."""
    times, values = np.asarray(times, float), np.asarray(values, float)
    if len(times) != len(values) or np.any(np.diff(times) <= 0):
        raise ValueError("pass increasing times (F,) and values (F, ...) with one entry per time")

    def at(t: float) -> np.ndarray:
        k = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2))
        a = np.clip((t - times[k]) / (times[k + 1] - times[k]), 0.0, 1.0)
        return (1 - a) * values[k] + a * values[k + 1]
    return at


def forward_run(material, params: dict, rho, frames, s0: float | None = None, prescribed=None, moving=None,
                v0=None, body=None, safety: float = 0.5, surface=False, eta_over_s0=ETA_OVER_S0,
                dt: float | None = None, track_energy: bool = True) -> ForwardRun:
    """Integrate the module docstring's equation over [0, frames[-1]] and save u, phi at ``frames``
    (times in ps, frames[0] = 0). ``rho`` (N,) density; ``s0``: the critical stretch (None: no
    damage), a number or one per bond as ``eta_over_s0``; ``prescribed`` (N,) bool with ``moving(t)``
    -> (N, 2) displacements (only the prescribed rows are read); ``v0`` (N, 2) initial velocity;
    ``body(t)`` -> (N, 2) force density; ``surface``: False (the exact-kinematics LPS), True (eq
    3.18, every missing lattice site beyond a free surface) or ``free(sites) -> bool``
    (``FreeSurface``'s: False beyond prescribed edges); ``dt``: the step (None: ``safety`` times
    the Verlet limit); ``track_energy``: False leaves ``ForwardRun.energy`` None (a force pass a
    frame less)."""
    frames = np.asarray(frames, float)
    if frames[0] != 0 or np.any(np.diff(frames) <= 0):
        raise ValueError("frames must start at t = 0 and increase")
    n = material.particles.n
    fixed = np.zeros(n, bool) if prescribed is None else np.asarray(prescribed, bool)
    if fixed.any() and moving is None:
        raise ValueError("prescribed nodes need moving(t): pass their displacement history")
    law = None if s0 is None else _smooth_step(s0, eta_over_s0)
    start = time.perf_counter()
    volume = np.asarray(material.particles.volume, float)
    mass = _mass(material, rho)
    dt = _time_step(material, params, mass, safety) if dt is None else positive("the step dt", dt)
    per_frame = np.maximum(np.ceil(np.diff(frames) / dt).astype(int), 1)
    kin = NonlinearBonds(material)
    law_force = kin.at(params) if surface is False else FreeSurface(material, params, None if surface is True else surface)
    index = DamageIndex(material.particles, material.bonds, material.bond_weight(params).detach())
    free = torch.as_tensor(~fixed)[:, None]
    m = torch.as_tensor(mass)[:, None]
    V = torch.as_tensor(volume)[:, None]
    u = torch.zeros(n, 2, dtype=torch.float64)
    v = torch.zeros_like(u) if v0 is None else torch.as_tensor(np.asarray(v0, float)).clone()
    v = v * free
    state = torch.zeros(len(material.i), dtype=torch.float64)
    intact = None if law is None else law.intact(state)

    def force(t, u, intact):
        f = law_force.force(u, intact)
        if body is not None:
            f = f + V * torch.as_tensor(np.asarray(body(t), float))
        return f * free

    def energy(u, v, intact):
        return float(0.5 * (m * v * v * free).sum() + law_force.strain_energy(u, intact)) if track_energy else None

    f = force(0.0, u, intact)
    ones = np.ones(len(material.i))
    saved_u, saved_phi, saved_g, saved_e = [u.numpy().copy()], [np.zeros(n)], [ones], [energy(u, v, intact)]
    t, steps = 0.0, 0
    for k, count in enumerate(per_frame):
        h = (frames[k + 1] - frames[k]) / count
        for _ in range(count):
            t += h
            steps += 1
            v_half = v + 0.5 * h * f / m
            u = u + h * v_half
            if fixed.any():
                u = torch.where(free, u, torch.as_tensor(np.asarray(moving(t), float)))
            if law is not None:
                state = law.update(state, kin.stretch(u))
                intact = law.intact(state)
            f = force(t, u, intact)
            v = (v_half + 0.5 * h * f / m) * free
        if not torch.isfinite(u).all():
            raise NumericalInstabilityError(f"the forward run blew up before t = {frames[k + 1]:g} ps with dt = {h:g}: "
                                            "lower safety")
        saved_u.append(u.numpy().copy())
        saved_phi.append(np.zeros(n) if law is None else index(intact).numpy())
        saved_g.append(ones if law is None else intact.numpy().copy())
        saved_e.append(energy(u, v, intact))
    return ForwardRun(frames, np.stack(saved_u), np.stack(saved_phi), np.stack(saved_g),
                      np.array(saved_e) if track_energy else None, float(dt), steps, time.perf_counter() - start)


def forward_runs(material, params: dict, rho, frames, s0s, eta_over_s0s=ETA_OVER_S0, prescribed=None, moving=None,
                 v0=None, body=None, safety: float = 0.5, surface=False, batch: int = 32,
                 threads: int | None = None) -> list[ForwardRun]:
    """``forward_run`` at each pair (s0s[k], eta_over_s0s[k]), with the body's own step (``surface``
    as ``forward_run``'s, a ``free(sites)`` asked about each copy's sites at the body's own
    coordinates): equal batches of at most ``batch`` pairs, each one run of ``material.copies``
    (copy c's bonds under pair c's law), the batches side by side on ``threads`` threads (None: the
    cores this process may use; ``bond_loops.claimed``) with one torch thread each (restored
    after). Each run's numbers are its own ``forward_run``'s to the bit; a step's fixed cost is
    shared by its batch. A run's ``energy`` is None (not tracked)."""
    s0s, widths = np.ravel(s0s).astype(float), np.ravel(eta_over_s0s).astype(float)
    if len(s0s) == 0 or len(widths) not in (1, len(s0s)):
        raise ValueError(f"pass at least one s0 and one eta_over_s0 per s0 (or one for all); got {len(s0s)} and "
                         f"{len(widths)}")
    widths = np.broadcast_to(widths, s0s.shape)
    n, bonds = material.particles.n, len(material.i)
    dt = _time_step(material, params, _mass(material, rho), safety)
    rho = np.broadcast_to(np.asarray(rho, float), (n,))
    threads = threads or len(os.sched_getaffinity(0))
    free = _per_copy(surface, material)
    batches = np.array_split(np.arange(len(s0s)), min(len(s0s), -(-len(s0s) // (batch * threads)) * threads))

    def task(t: int) -> list[ForwardRun]:
        pick = batches[t]
        k = len(pick)
        tiled = [None if a is None else np.tile(a, (k,) + (1,) * (np.ndim(a) - 1)) for a in (rho, prescribed, v0)]
        run = forward_run(material.copies(k), params, tiled[0], frames, np.repeat(s0s[pick], bonds), tiled[1],
                          _tiled_in_time(moving, k), tiled[2], _tiled_in_time(body, k), surface=free,
                          eta_over_s0=np.repeat(widths[pick], bonds), dt=dt, track_energy=False)
        return [ForwardRun(run.t, run.u[:, c * n:(c + 1) * n], run.phi[:, c * n:(c + 1) * n],
                           run.intact[:, c * bonds:(c + 1) * bonds], None, run.dt, run.steps, run.wall_time_s / k)
                for c in range(k)]
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return [run for runs in bond_loops.claimed(task, len(batches), threads, redo=False) for run in runs]
    finally:
        torch.set_num_threads(before)


def _per_copy(surface, material):
    """``surface`` for ``material.copies``: a ``free(sites)`` asked at the sites moved back into the
    body (``Material.in_body``); True, False as given."""
    if isinstance(surface, bool):
        return surface
    return lambda sites: surface(material.in_body(sites))


def _tiled_in_time(field, k: int):
    """t -> ``field(t)`` (N, ...) repeated for k copies (None stays None)."""
    return None if field is None else lambda t: np.tile(field(t), (k, 1))


def _mass(material, rho) -> np.ndarray:
    """The nodal masses rho V (``MASS`` units), rho checked positive."""
    rho = np.broadcast_to(np.asarray(rho, float), (material.particles.n,))
    if np.any(rho <= 0):
        raise ValueError("the density rho must be positive at every node: coarse-grain with a larger cone radius")
    return MASS * rho * np.asarray(material.particles.volume, float)


def _smooth_step(s0, eta_over_s0) -> SmoothStep:
    """Eq 3.10's law at s0 with the width eta_over_s0 s0 (numbers, or one per bond)."""
    s0 = torch.as_tensor(positive("s0", s0, "pass the critical stretch"), dtype=torch.float64)
    width = torch.as_tensor(positive("eta_over_s0", eta_over_s0, "pass eq 3.10's width over s0"), dtype=torch.float64)
    return SmoothStep(s0, width * s0)


def _time_step(material, params, mass, safety) -> float:
    """safety x the Verlet limit of the intact linearised operator (``stable_time_step``)."""
    with torch.no_grad():
        values = material.numeric_stiffness(params, None).numpy()
    pat = material.pattern
    K = scipy.sparse.csc_matrix((values, (pat.rows, pat.cols)), shape=(pat.n, pat.n))
    return stable_time_step(K, np.repeat(mass, 2), safety)
