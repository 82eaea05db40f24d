"""Explicit dynamics: velocity Verlet for M u'' = f(u) - gamma M u' with lumped masses
m_i = rho V_i, a stable time-step estimate, and detection of numerical blow-up.

Stability: per vibration mode of M^-1 K (frequency omega, omega^2 an eigenvalue) Verlet is
stable iff omega dt < 2, so dt_crit = 2 / sqrt(lambda_max(M^-1 K)); ``stable_time_step``
returns safety * dt_crit with lambda_max from Lanczos on M^-1/2 K M^-1/2.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bayespd.linalg.assembly import to_numpy
from bayespd.solvers import verlet_loops
from bayespd.solvers.linear import as_matvec, hessian_operator, largest_eigenvalue


class NumericalInstabilityError(RuntimeError):
    """A time integration blew up (non-finite values or exponential growth): the message
    names the step limit to go below."""


@dataclass
class Trajectory:
    """Saved states ``u`` (saves, n[, batch]) at times ``t``; ``final`` is the last state.

    Verlet also fills ``v`` (saved velocities), ``final_v``, and per step ``kinetic`` and
    ``potential`` = V(u_n) - V(u_0) (trapezoidal work of f, exact for a linear force)."""

    t: np.ndarray
    u: torch.Tensor
    final: torch.Tensor
    v: torch.Tensor | None = None
    final_v: torch.Tensor | None = None
    kinetic: np.ndarray | None = None
    potential: np.ndarray | None = None

    @property
    def energy(self) -> np.ndarray:
        """Total energy kinetic + V(u_n) - V(u_0) per step (Verlet)."""
        return self.kinetic + self.potential


class GrowthMonitor:
    """Flags a size s_n (an energy, a squared distance) that is non-finite or exceeds
    ``factor`` times its largest value over steps <= max(n // 2, 1). Bounded dynamics grow at
    most polynomially (from rest an energy grows like t^2: 4x per doubling of n); an unstable
    mode grows geometrically, by g per step, and trips this after about 2 log(factor) / log g
    steps."""

    def __init__(self, steps: int, factor: float = 1e8):
        self.prefix_max = np.zeros(steps + 1)
        self.factor = factor

    def __call__(self, n: int, s: float) -> bool:
        if not np.isfinite(s):
            return True
        self.prefix_max[n] = max(self.prefix_max[n - 1], s) if n else s
        ref = self.prefix_max[max(n // 2, 1)]
        return bool(ref > 0 and s > self.factor * ref)


def lumped_mass(particles, rho, dofs=None) -> torch.Tensor:
    """Mass per dof, m_i = rho V_i repeated over the dim components (node-major), optionally
    restricted to the indices ``dofs`` (e.g. the free dofs). ``rho``: scalar or (N,)."""
    rho = torch.as_tensor(rho, dtype=torch.float64)
    if not bool(torch.all(torch.isfinite(rho)) and torch.all(rho > 0)):
        raise ValueError("the mass density rho must be finite and positive")
    m = (rho * torch.as_tensor(particles.volume)).expand(particles.n)
    m = m.repeat_interleave(particles.dim)
    return m if dofs is None else m[torch.as_tensor(dofs)]


def critical_time_step(stiffness, mass) -> float:
    """2 / sqrt(lambda_max(M^-1 K)): the Verlet limit (``stiffness`` a scipy matrix or a
    numpy matvec; ``mass`` per dof)."""
    s = 1 / np.sqrt(to_numpy(mass))
    K = as_matvec(stiffness)
    return 2 / np.sqrt(largest_eigenvalue(lambda v: s * K(s * v), len(s)))


def stable_time_step(stiffness, mass, safety: float = 0.9) -> float:
    """safety * 2 / sqrt(lambda_max(M^-1 K)); safety < 1 also covers Lanczos converging
    to lambda_max from below and stiffening of a nonlinear force."""
    if not 0 < safety <= 1:
        raise ValueError("safety must lie in (0, 1]")
    return safety * critical_time_step(stiffness, mass)


def velocity_verlet(force, mass, u0, dt: float, steps: int, v0=None, damping: float = 0.0,
                    save_every: int = 0, stiffness=None) -> Trajectory:
    """Integrate M u'' = f(u) - damping M u' by velocity Verlet (second order; the damping
    half-kick is implicit, so gamma needs no step restriction of its own).

    ``force(u)`` is f = -grad V (internal + external) for u of shape (n,); ``mass`` per dof.
    ``save_every`` k > 0 keeps every k-th state. Blow-up raises NumericalInstabilityError with
    the limit 2 / sqrt(lambda_max(M^-1 K)), K = ``stiffness`` (scipy or matvec) or the
    force's Hessian at u0.
    """
    m = torch.as_tensor(mass, dtype=u0.dtype)
    if u0.dim() != 1 or m.shape != u0.shape:
        raise ValueError("u0 must be (n,) and mass must have one entry per dof")
    _check_steps(dt, steps, save_every)
    u = u0.clone()
    v = torch.zeros_like(u) if v0 is None else v0.clone()
    f = force(u)
    kinetic, potential = np.zeros(steps + 1), np.zeros(steps + 1)
    kinetic[0] = 0.5 * float((m * v * v).sum())
    monitor = GrowthMonitor(steps)
    saves = _Saver(u, save_every)
    saves_v = _Saver(v, save_every)
    compiled = verlet_loops.usable(u, v, f, m)
    if compiled and steps:
        drifted = verlet_loops.drift(u, v, f, m, dt, damping)
    for n in range(1, steps + 1):
        if compiled:  # one pass: this step's kick and energies, the next step's drift
            v_half, u_new = drifted
            f_new = force(u_new)
            v, work, kinetic[n], drifted = verlet_loops.kick(v_half, f_new, m, dt, damping, f, u_new, u, n < steps)
            potential[n] = potential[n - 1] - work
        else:
            v_half = v + 0.5 * dt * (f / m - damping * v)
            u_new = u + dt * v_half
            f_new = force(u_new)
            v = (v_half + 0.5 * dt * f_new / m) / (1 + 0.5 * damping * dt)
            potential[n] = potential[n - 1] - 0.5 * float(((f + f_new) * (u_new - u)).sum().detach())
            kinetic[n] = 0.5 * float((m * v * v).sum().detach())
        u, f = u_new, f_new
        if monitor(n, kinetic[n]):
            dt_crit = critical_time_step(stiffness if stiffness is not None else hessian_operator(force, u0), m)
            raise NumericalInstabilityError(
                f"velocity Verlet blew up at step {n} (t = {n * dt:g}): the kinetic energy grew "
                f"to {kinetic[n]:.3g} from at most {monitor.prefix_max[max(n // 2, 1)]:.3g} by step {max(n // 2, 1)}. "
                f"dt = {dt:g} against the limit 2/sqrt(lambda_max(M^-1 K)) = {dt_crit:g}: "
                f"{_fix(dt, dt_crit)} (stable_time_step gives a safe value)")
        saves(n, u)
        saves_v(n, v)
    return Trajectory(saves.times(dt), saves.stack(), u, saves_v.stack(), v, kinetic, potential)


def _fix(dt: float, limit: float) -> str:
    """What to do about a blow-up, given the linear step limit at the start."""
    if dt > limit:
        return f"reduce dt below {limit:g}"
    return f"dt is below it, so the force stiffened during the run: reduce dt further (e.g. to {dt / 2:g})"


def _check_steps(dt, steps, save_every):
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be finite and positive, got {dt}")
    if int(steps) != steps or steps < 0 or int(save_every) != save_every or save_every < 0:
        raise ValueError("steps and save_every must be non-negative integers")


class _Saver:
    """Keeps the initial state and every k-th state (k = 0: none after the initial)."""

    def __init__(self, u0: torch.Tensor, every: int):
        self.every, self.steps, self.states = every, [0], [u0.clone()]

    def __call__(self, n: int, u: torch.Tensor):
        if self.every and n % self.every == 0:
            self.steps.append(n)
            self.states.append(u.clone())

    def times(self, dt: float) -> np.ndarray:
        return np.asarray(self.steps) * dt

    def stack(self) -> torch.Tensor:
        return torch.stack(self.states)
