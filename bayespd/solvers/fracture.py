"""Stochastic fracture: overdamped Langevin dynamics (Dodwell 2019 eq 4) of a ``Scene`` that
declares a damage law and noise, at fixed params (``Scene.at``), with the exact bond force and a
displacement-controlled ramp,

    dU = -eta^-1 C grad V(U; mu, lambda(t)) dt + sqrt(2 C) dB,

V of eq 3 on the free dofs (the moving Dirichlet layers enter through f_int), mu from the damage
law (critical stretch or smoothed step, irreversible; or the damage ODE, which uses dt).

Step n (lambda_n from the ramp): one step of ``Langevin``'s linearly implicit theta-scheme with
operator A = T + eps I, T the tangent of ``body.LoadedBody`` (bond-based: the Hessian with tensile
geometric stiffness; LPS: the damaged linearised stiffness) taken when the intact fractions
last changed (by more than ``refactor_tol``; the sharp law: whenever a bond breaks), then
the damage update with the new stretch. A change costs no factorisation: a factor made at
the start is updated by Woodbury for the changed bonds (``woodbury.LocallyUpdated``; exact
for LPS), and for a bond-based body, whose T also moves with u through its geometric part
(a fraction <= max(e/r) ~ s0 of T), conjugate gradients solve with the exact T,
preconditioned by that factor (``woodbury.Refined``, about two iterations a step), or, with
``tangent="lagged"``, the steps use that updated operator itself: a W-method (linearly
implicit Euler with an approximate Jacobian, Hairer & Wanner 1996 §IV.7), with the same
fixed points and order, whose chord iteration contracts by about the geometric fraction
s0 per step; one solve a step instead of about three, and no assembly (over 8 seeds its
mean failure load, peak load and crack length are within one standard error of the exact
tangent's, ``benchmarks/fracture.py``). The factor
is made afresh only when the dofs solved for change (a piece came loose), when the bonds
changed since touch more than ``max_rank`` dofs, or when conjugate gradients need more
than REFRESH_ITERATIONS. With ``hold`` the ramp waits while bonds break: lambda
advances only after a step in which no bond broke, the stochastic counterpart of seed
004 §5.2's re-solve until no new bond breaks.

Deterministic limit: with C = sigma^2 I and the mobility M = sigma^2 / eta fixed, theta = 1,
each step is (I + a A) U' = U + a (f(U) + A U) + sqrt(2 dt) sigma xi, a = M dt; for
a lambda_min(A) >> 1 this is one Newton step (lagged tangent) of ``quasistatic.equilibrium``
plus the random force sqrt(2 / dt) sigma / M xi, which vanishes with sigma: the run then
follows the quasi-static path (tested). Pieces that come loose are handled as in ``quasistatic``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from bayespd import bond_loops
from bayespd.damage import DamageIndex, crack_length, crack_path
from bayespd.linalg import trailing
from bayespd.solvers.dynamics import NumericalInstabilityError
from bayespd.solvers.langevin import Langevin
from bayespd.solvers.noise import Covariance
from bayespd.linalg.woodbury import LocallyUpdated, Refined


COLUMN_TILE = 4  # side (in spacings h) of the tiles of dofs whose Woodbury columns are solved together
ZONE_MARGIN = 2  # horizons around the damage that a fresh factor's region takes in (``run``'s zone)
REFRESH_ITERATIONS = 8  # conjugate-gradient iterations per step beyond which the factor is renewed
TANGENTS = ("exact", "lagged")  # the operators of the steps (module docstring)


def check_tangent(tangent: str) -> None:
    if tangent not in TANGENTS:
        raise ValueError(f'tangent must be "exact" or "lagged", got {tangent!r}')


@dataclass
class Realisation:
    """One run: per step ``t``, ``load_factor``, ``reaction`` (steps, dim) on the loaded
    particles, ``broken`` bond count and ``crack_length`` (of ``crack_path`` of phi); at the
    end ``phi`` (N,), the crack ``path`` (k, dim), ``u`` (N, dim) and ``intact``; ``seed``."""

    t: np.ndarray
    load_factor: np.ndarray
    reaction: np.ndarray
    broken: np.ndarray
    crack_length: np.ndarray
    phi: np.ndarray
    path: np.ndarray
    u: torch.Tensor
    intact: torch.Tensor
    seed: int | None

    @property
    def peak(self) -> int:
        """Index of the step with the largest reaction |R| (under strong noise the reaction
        fluctuates, and its peak overstates the failure load)."""
        return int(np.argmax(np.linalg.norm(self.reaction, axis=1)))

    @property
    def first_failure(self) -> int | None:
        """Index of the first step that ends with a broken bond (None: none broke)."""
        k = np.flatnonzero(self.broken > 0)
        return int(k[0]) if len(k) else None


class StochasticFracture:
    """Dodwell 2019 eq 4 with damage for ``scene`` (a ``Scene``) at ``params``: the scene's
    ``damage`` law and noise covariance C on its free dofs (``Scene.covariance``), temperature
    ``eta``, and the theta of the scheme (1: linearly implicit Euler, robust for the nonlinear
    force). ``reaction_scale`` multiplies the recorded reactions: a material whose force is
    linear in a modulus K runs as the unit-modulus body at temperature eta / K (the same
    dynamics), whose factor then serves every K (``bayespd.scenes.notched_plate``), and
    reports K times its reactions."""

    def __init__(self, scene, params: dict, eta: float, theta: float = 1.0, reaction_scale: float = 1.0):
        if scene.damage is None:
            raise ValueError("stochastic fracture needs a damage law: declare it in the scene, "
                             "e.g. Scene(..., damage=CriticalStretch(s0))")
        self.C = scene.covariance  # refuses a scene without noise, naming the fix
        if not 0.5 <= theta <= 1:
            raise ValueError("theta must lie in [1/2, 1]: the operator is needed for stability")
        if not reaction_scale > 0:
            raise ValueError(f"reaction_scale must be positive, got {reaction_scale}")
        self.body, self.damage, self.eta, self.theta = scene.at(params), scene.damage, eta, theta
        self.reaction_scale = float(reaction_scale)

    def run(self, load_factors, dt: float, seed, hold: bool = True, max_steps: int | None = None,
            path_threshold: float = 0.4, refactor_tol: float = 1e-2, max_rank: int = 512,
            tangent: str = "exact", zone=None) -> Realisation:
        """March through ``load_factors`` (one per step; with ``hold`` a step that breaks a bond
        (intact fraction crossing 1/2) is repeated at the same factor, up to ``max_steps``
        steps in all, default 10 per factor). The operator follows the intact fractions when
        one has moved by more than ``refactor_tol`` since it last did (the sharp law: whenever
        a bond breaks), by a Woodbury update of rank up to ``max_rank`` (0: factorise at
        every change). ``tangent``: "exact" or "lagged" (bond-based; module docstring).
        ``zone``: (N,) mask of the particles where the crack may run (with CHOLMOD their dofs
        are ordered last in the factor, and the Woodbury columns need no solves,
        ``woodbury.LocallyUpdated(region=...)``; a factor made after damage also takes in
        the particles within ZONE_MARGIN horizons of the damaged bonds' ends).
        ``seed``: an int or a ``torch.Generator``; the same seed reproduces the run bit for
        bit. Raises NumericalInstabilityError on a blow-up."""
        check_tangent(tangent)
        body, law = self.body, self.damage
        if zone is not None and np.shape(zone) != (body.particles.n,):
            raise ValueError(f"zone must be a mask of the {body.particles.n} particles")
        zone = None if zone is None or not trailing.available() else np.asarray(zone, dtype=bool)
        exact = tangent == "exact" and body.geometric
        lams = np.asarray(load_factors, dtype=float)
        max_steps = max_steps or 10 * len(lams)
        gen = seed if isinstance(seed, torch.Generator) else torch.Generator().manual_seed(int(seed))
        damage_index = DamageIndex(body.particles, body.bonds)
        state = law.init(body.n_bonds)
        intact = operated = law.intact(state)
        broken = intact < 0.5
        u = torch.zeros(body.particles.n, body.particles.dim)
        pieces = body.floating_pieces()  # its own: runs in lock-step share the body
        base = self._factorised(intact, u, max_rank, zone, pieces)
        step, A = self._stepper(intact, u, base, exact)
        rec = {k: [] for k in ("t", "lam", "reac", "broken", "length")}
        k = n = 0
        length, f, lam = 0.0, None, None
        while k < len(lams) and n < max_steps:
            n += 1
            held = lams[k] == lam  # u is where the last step left it: f_int(u) is known
            lam = lams[k]
            u = step(body.move(u, lam), lam, intact, dt, gen, f if held else None)
            if not bool(torch.isfinite(u).all()):
                raise NumericalInstabilityError(
                    f"the stochastic fracture run blew up at step {n} (load factor {lams[k]:g}): "
                    "reduce dt, or the noise (eta), or give the body eps > 0")
            bonds_now = body.kinematics.shared_components(u)  # one torch gather for both, or None
            state = law.update(state, body.kinematics.stretch(u, bonds_now), dt)
            intact = law.intact(state)
            moved, broken, n_broken, broke = _tally(intact, operated, broken)
            stale = getattr(A, "iterations", 0) > REFRESH_ITERATIONS
            if stale or moved > refactor_tol:
                operated = intact
                base = (self._factorised(intact, u, max_rank, zone, pieces) if stale
                        else self._updated(base, intact, u, max_rank, zone, pieces))
                step, A = self._stepper(intact, u, base, exact)
            if broke:
                phi = damage_index(intact)
                length = crack_length(crack_path(body.particles, phi, path_threshold))
            rec["t"].append(n * dt)
            rec["lam"].append(lams[k])
            f = body.internal(u, intact, bonds_now)
            rec["reac"].append(self.reaction_scale * body.reaction(u, intact, f).numpy())
            rec["broken"].append(n_broken)
            rec["length"].append(length)
            k += not (hold and broke)
        phi = damage_index(intact)
        return Realisation(np.asarray(rec["t"]), np.asarray(rec["lam"]), np.asarray(rec["reac"]),
                           np.asarray(rec["broken"]), np.asarray(rec["length"]), phi.numpy(),
                           crack_path(body.particles, phi, path_threshold), u, intact,
                           None if isinstance(seed, torch.Generator) else int(seed))

    def _factorised(self, intact, u, max_rank: int, zone, pieces) -> "_Operated":
        """A fresh operator at (intact, u) on the dofs still solved for (``pieces``: the run's
        ``FloatingPieces``)."""
        body = self.body
        active = body.active(intact, pieces)
        A = None
        if len(active):
            tiles = body.tiles(active, COLUMN_TILE * body.particles.h)
            A = LocallyUpdated(body.operator(intact, active, u), max_rank, groups=tiles,
                               region=self._region(active, intact, zone))
        return _Operated(A, A, intact, u, active)

    def _region(self, active, intact, zone) -> np.ndarray | None:
        """The positions in ``active`` of the dofs of the zone's particles and of those
        within ZONE_MARGIN horizons of a damaged bond's end (None: no zone)."""
        if zone is None:
            return None
        body = self.body
        inside = zone.copy()
        damaged = torch.nonzero(torch.as_tensor(intact) < 1).reshape(-1).numpy()
        if len(damaged):
            x = np.asarray(body.particles.x)
            ends = np.unique(np.concatenate([body.bonds.i[damaged], body.bonds.j[damaged]]))
            near = cKDTree(x[ends]).query(x, distance_upper_bound=ZONE_MARGIN * float(body.params["delta"]))[0]
            inside |= np.isfinite(near)
        region = np.flatnonzero(inside[active // body.particles.dim])
        return region if len(region) else None

    def _updated(self, base: "_Operated", intact, u, max_rank: int, zone, pieces) -> "_Operated":
        """The factor at ``intact``: base's, updated by the change since it was made (the
        damaged zone's tangent at u, the rest at base's u), or a fresh one when the active
        dofs changed or the change is too large for a Woodbury update."""
        active = self.body.active(intact, pieces)
        if base.factored is not None and np.array_equal(active, base.active):
            change = self.body.operator_change(base.intact, intact, active, base.u, u)
            A = base.factored.changed(change)
            if A is not None:
                return _Operated(A, base.factored, base.intact, base.u, active)
        return self._factorised(intact, u, max_rank, zone, pieces)

    def _stepper(self, intact, u, operated: "_Operated", exact: bool):
        """(step, A): step(u, lam, intact, dt, gen, f) -> u, one theta-step with the force at
        the given intact fractions (f: f_int(u) when known) and the operator A on
        ``operated``'s active dofs: its ``LocallyUpdated`` operator, or with ``exact`` the
        exact tangent at u, solved by conjugate gradients preconditioned with it (``Refined``)."""
        body, active = self.body, operated.active
        if len(active) == 0:  # everything came loose: nothing left to move
            return (lambda u, *_: u), None
        idx = torch.as_tensor(active)
        C = self.C
        if len(active) < C.n:  # restrict C to the dofs still solved for
            pos = np.searchsorted(body.constraints.free_dofs, active)
            C = Covariance(C.d[pos], None if C.G is None else C.G[pos])
        current = {}

        def force(U):
            u, f = current["u"], current["f"]
            if f is not None and torch.equal(U, u.view(-1)[idx]):  # at the step's start: known
                return (f + current["lam"] * body.load - body.eps * u).view(-1)[idx]
            u = u.clone()
            u.view(-1)[idx] = U
            return body.residual(u, current["lam"], current["intact"]).view(-1)[idx]

        A = operated.A
        if exact:  # the exact tangent at u, the factor of a stale one preconditions it
            fresh = A.delta is None and operated.u is u  # just factorised at (intact, u)
            T = A.A0 if fresh else body.operator(intact, active, u)
            A = Refined(lambda v: T @ v, A)
        langevin = Langevin(force, C, self.eta, operator=A)

        def step(u, lam, intact_now, dt, gen, f=None):
            current.update(u=u, lam=lam, intact=intact_now, f=f)
            U = langevin.run(u.view(-1)[idx], dt, 1, theta=self.theta, generator=gen).final
            out = u.clone()
            out.view(-1)[idx] = U
            return out

        return step, A


def _tally(intact, operated, broken) -> tuple[float, torch.Tensor, int, bool]:
    """``bond_loops.tally`` where it can, else the same by torch."""
    if bond_loops.usable(intact, operated):
        return bond_loops.tally(intact, operated, broken)
    now = intact < 0.5
    return float((intact - operated).abs().max()), now, int(now.sum()), not torch.equal(now, broken)


@dataclass
class _Operated:
    """The factored operator ``A`` of the steps (LPS) or their preconditioner (bond-based),
    the fresh factorisation it was updated from (``factored``), and the intact fractions,
    displacement and active dofs that one was made at."""

    A: LocallyUpdated | None
    factored: LocallyUpdated | None
    intact: torch.Tensor
    u: torch.Tensor
    active: np.ndarray
