"""Quasi-static loading with bond breaking (You 2023 §5.2): at each load step solve the
equilibrium, update the damage, and re-solve at the same load until no new bond breaks.

A load factor lambda scales every Dirichlet value and every load of a ``Scene`` (displacement
control: a layer moved by lambda times its value; force control: loads times lambda).
Equilibrium is the stationary point of the potential of Dodwell 2019 eq 3 with the exact bond
kinematics of ``bayespd.nonlinear`` at the current intact fractions mu:

    r(u) = f_int(u; mu) + lambda p - eps u = 0   on the free dofs.

Solver: Newton, u <- u + (T + eps I)^-1 r, T the tangent of ``body.LoadedBody`` (the scene at
fixed params), refactorised only when the iteration slows down (``equilibrium``). With eps = 0
pieces that come loose are dropped from the solve (``body``); under force control a loaded piece that
comes loose cannot carry its load: the run stops there (``separated``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bayespd.damage import DamageIndex, DamageODE
from bayespd.linalg.sparse import ConvergenceError
from bayespd.solvers.body import LoadedBody

@dataclass
class QuasiStaticResult:
    """Per load step k: ``load_factors``, ``displacement`` and ``reaction`` (steps, dim) of
    the loaded particles, ``broken`` bond count, ``damage`` index phi (steps, N),
    ``iterations`` (Newton, summed over re-solves) and ``resolves`` (equilibria solved);
    final ``u`` (N, dim), damage ``state`` and ``intact`` fractions. ``separated``: a loaded
    piece came loose under force control and the run stopped after the last step listed."""

    load_factors: np.ndarray
    displacement: np.ndarray
    reaction: np.ndarray
    broken: np.ndarray
    damage: np.ndarray
    iterations: np.ndarray
    resolves: np.ndarray
    u: torch.Tensor
    state: torch.Tensor | None
    intact: torch.Tensor
    separated: bool = False

    @property
    def first_failure(self) -> int | None:
        """Index of the first step that ends with a broken bond (None: none broke)."""
        k = np.flatnonzero(self.broken > 0)
        return int(k[0]) if len(k) else None

    @property
    def peak(self) -> int:
        """Index of the step with the largest reaction |R|."""
        return int(np.argmax(np.linalg.norm(self.reaction, axis=1)))


def equilibrium(body: LoadedBody, u: torch.Tensor, lam: float, intact, tangent, active,
                rtol: float = 1e-10, max_iter: int = 50):
    """Newton from u (prescribed dofs already at lambda), ``tangent(u)`` giving the factor of
    T + eps I, taken at the first iteration and again whenever one reduced |r| less than 10x
    (a lagged tangent: most solves factorise once); returns (u, iterations). Converged when
    |r| <= rtol |f_int| (all dofs) or when the update falls below 1e-13 h: the extension
    |y| - |xi| carries a rounding error of ~1e-16 |xi|, so at strains below ~1e-6 the residual
    stalls above rtol while u is exact to rounding. Raises ConvergenceError."""
    idx = torch.as_tensor(active)
    u = u.clone()
    flat = u.view(-1)
    factor, previous = None, np.inf
    for it in range(max_iter):
        f = body.internal(u, intact)
        r = (f + lam * body.load - body.eps * u).view(-1)[idx]
        rn = float(r.norm())
        if not np.isfinite(rn):
            break
        if rn <= rtol * float(f.norm()):
            return u, it
        if factor is None or rn > 0.1 * previous:
            factor = tangent(u)
        previous = rn
        du = torch.from_numpy(np.asarray(factor.solve(r.numpy())))
        flat[idx] += du
        if float(du.abs().max()) <= 1e-13 * body.particles.h:
            return u, it + 1
    raise ConvergenceError(
        f"the equilibrium at load factor {lam:g} did not converge in {max_iter} Newton "
        f"iterations (residual {rn:.3g}): stretches far beyond s0, or a mechanism formed "
        "(LPS: its tangent has no geometric stiffness); use smaller load steps, or eps > 0")


def quasi_static(scene, params: dict, load_factors, rtol: float = 1e-10, max_iter: int = 50,
                 damage_tol: float = 0.0) -> QuasiStaticResult:
    """Step ``scene`` (a ``Scene``) at ``params`` through ``load_factors`` (any sequence:
    loading, unloading, reloading); after each equilibrium update the scene's damage law
    (``CriticalStretch`` or ``SmoothStep``, irreversible) with the stretch and re-solve until
    no intact fraction changes by more than ``damage_tol`` (You 2023 §5.2; the sharp law stops
    exactly with 0, the smoothed step needs a tolerance, e.g. 1e-6). A scene without damage:
    nonlinear elasticity, no breaking and no damage state."""
    body, damage = scene.at(params), scene.damage
    if isinstance(damage, DamageODE):
        raise TypeError("the damage ODE is rate-dependent and quasi-static loading has no time: "
                        "use bayespd.solvers.fracture (Langevin with a time step) for it")
    p, nb = body.particles, body.n_bonds
    state = damage.init(nb) if damage is not None else None
    intact = damage.intact(state) if damage is not None else torch.ones(nb)
    u = torch.zeros(p.n, p.dim)
    active = body.active(intact)
    tangent = body.tangent(intact, active)
    damage_index = DamageIndex(p, body.bonds)
    rec = {k: [] for k in ("lam", "disp", "reac", "broken", "phi", "its", "solves")}
    separated = False
    for lam in np.asarray(load_factors, dtype=float):
        u = body.move(u, lam)
        its = solves = 0
        while True:
            u, n = equilibrium(body, u, lam, intact, tangent, active, rtol, max_iter)
            its, solves = its + n, solves + 1
            if damage is None:
                break
            state = damage.update(state, body.kinematics.stretch(u))
            new = damage.intact(state)
            changed = float((new - intact).abs().max()) > damage_tol
            intact = new
            if not changed:
                break
            active = body.active(intact)
            separated = lam != 0 and bool(body.load.abs().sum(1)[_dropped(body, active)].any())
            if separated:
                break
            tangent = body.tangent(intact, active)
        rec["lam"].append(lam)
        rec["disp"].append(body.mean_displacement(u).numpy())
        rec["reac"].append(body.reaction(u, intact).numpy())
        rec["broken"].append(int((intact < 0.5).sum()))
        rec["phi"].append(damage_index(intact).numpy())
        rec["its"].append(its)
        rec["solves"].append(solves)
        if separated:
            break
    return QuasiStaticResult(np.asarray(rec["lam"]), np.asarray(rec["disp"]), np.asarray(rec["reac"]),
                             np.asarray(rec["broken"]), np.asarray(rec["phi"]), np.asarray(rec["its"]),
                             np.asarray(rec["solves"]), u, state, intact, separated)


def _dropped(body: LoadedBody, active: np.ndarray) -> np.ndarray:
    """Mask of the particles with a free dof that is not solved for."""
    mask = np.zeros(body.particles.n * body.particles.dim, dtype=bool)
    mask[body.constraints.free_dofs] = True
    mask[active] = False
    return torch.as_tensor(mask.reshape(body.particles.n, -1).any(1))
