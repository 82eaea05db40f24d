"""A reduced-order stand-in for a Scene's static solve (Cui, Marzouk & Willcox 2015): the
full operator projected on a POD basis V of full-model snapshots over the prior, kept affine
in the moduli, K_r(theta) = sum_t Theta_t(moduli) V^T A_t(delta) V, with each V^T A_t V (and
each projected load) a cubic spline in delta. Each evaluation costs an r x r solve, whatever
the particle count; it is differentiable (twice) in the moduli, delta and the load factor.

Why splines in delta and not an empirical interpolation: A_t depends on delta through the bond
weights omega * beta and the weighted volumes m, a smooth (C1 with ``rule="smooth"``) function of
one scalar; a cubic spline of the r x r blocks, refined until the reduced solution at the
interval midpoints agrees with the exactly projected one to a quarter of the tolerance, costs
one assembly per node once and nothing per particle online.

The basis is POD (``basis.pod``); its rank is the smallest whose largest observation error on
held-out draws (full solves not used for the basis) is within ``tolerance`` / 2, else the build
stops with an error. ``error_estimate`` bounds nothing but estimates the observation error at a
draw from the residual without a factorisation (``estimator``).
"""
from __future__ import annotations

import time
import warnings

import numpy as np
import torch

from bayespd.reduced.affine import Terms, check_reducible, coefficients
from bayespd.reduced.basis import pod
from bayespd.reduced.estimator import ErrorEstimator
from bayespd.reduced.piecewise import Piecewise, chebyshev_points, check_points


def breakpoints(bonds, low: float, high: float) -> np.ndarray:
    """low, the horizons in (low, high) where a bond length's partial volume switches on or
    saturates (delta = r -/+ h/2), and high; evenly spaced eighths when the lengths are too
    many to list (irregular particles)."""
    r = np.unique(np.round(bonds.length / bonds.h, 9)) * bonds.h
    kinks = np.concatenate([r - bonds.h / 2, r + bonds.h / 2])
    kinks = np.unique(np.round(kinks[(kinks > low) & (kinks < high)], 12))
    if len(kinks) > 64:
        kinks = np.linspace(low, high, 9)[1:-1]
    return np.concatenate([[low], kinks, [high]])


class ToleranceMissed(ValueError):
    """The reduced model misses its tolerance (the basis' rank or the polynomials in delta):
    more draws (snapshots) or a larger tolerance may meet it."""


class ReducedScene:
    """A Scene's ``predict``/``solve`` from a reduced basis (module docstring).

    ``scene``: the full scene (with an observation; direct or PCG: the snapshots are its solves);
    ``draws``: params dicts over
    the prior (K, G, delta, ...), the last ``validation`` of them held out to choose the rank;
    ``tolerance``: the largest observation error allowed, in the data's units (e.g. 1 % of the
    noise sd); ``delta_range``: the horizons the splines cover (default [h, delta_max], the
    support of the default prior); ``estimates``: how many draws of a fit get the error estimate
    (``diagnostics``; evenly spaced, each costs O(bonds); None: every draw). ``report`` holds the
    build's figures.
    """

    def __init__(self, scene, draws: list[dict], tolerance: float, *, validation: int | None = None,
                 delta_range: tuple[float, float] | None = None, max_pieces: int = 256,
                 estimates: int | None = 100):
        start = time.perf_counter()
        check_reducible(scene)
        if scene.observation is None:
            raise ValueError("the reduced model predicts observations: give the scene an observation")
        if not tolerance > 0:
            raise ValueError(f"tolerance must be > 0 (an observation error in the data's units), got {tolerance}")
        self.scene, self.tolerance, self.estimates = scene, float(tolerance), estimates
        self.material, self.particles, self.observation = scene.material, scene.particles, scene.observation
        self.param_names = scene.param_names
        self._out_shape = (self.observation.n, self.particles.dim)
        low, high = delta_range or (scene.particles.h, scene.material.bonds.delta_max)
        draws = [{k: float(d[k]) for k in self.param_names} for d in draws]
        validation = max(4, len(draws) // 5) if validation is None else validation
        if len(draws) < validation + 4:
            raise ValueError(f"{len(draws)} draws: the basis needs >= 4 and {validation} are held out "
                             "to validate it; give more draws")
        outside = [d["delta"] for d in draws if not low <= d["delta"] <= high]
        if outside:
            raise ValueError(f"draws with delta {outside[:3]} lie outside delta_range [{low}, {high}]")
        moduli = self.material.moduli_names
        self.reference = {k: float(np.median([d[k] for d in draws])) for k in moduli}
        self.theta_ref = coefficients(self.material, self.reference)
        if bool(torch.any(self.theta_ref == 0)):
            raise ValueError(f"a term coefficient is zero at the reference moduli {self.reference} (the "
                             "draws' median), and the others are scaled by it: give draws with another median")
        shapes = np.array([self._shape(d) for d in draws])
        self.shape_range = (shapes.min(axis=0), shapes.max(axis=0))

        t0 = time.perf_counter()
        full = np.stack([self._full_solve(d) for d in draws], axis=1)
        snapshot_s = time.perf_counter() - t0
        V, singular = pod(full[:, :-validation], 0.0)  # every direction; the rank is chosen below
        t0 = time.perf_counter()
        thetas = np.stack([(coefficients(self.material, d) / self.theta_ref).numpy() for d in draws])
        self._full = self._operators(V, low, high, max_pieces, thetas)
        operators_s = time.perf_counter() - t0
        held = draws[-validation:]
        observed = self._observed(full[:, -validation:])
        errors = self._choose_rank(held, observed)
        self.estimator = ErrorEstimator(self, {**self.reference, "delta": float(np.median([d["delta"] for d in draws]))})
        truth = np.abs(self._predict_numpy(held) - observed).max(axis=1)
        self.report = {
            "rank": self.rank, "snapshots": V.shape[1], "validation_draws": validation,
            "validation_error_max": errors[-1], "validation_error_by_rank": errors,
            "singular_values": (singular / singular[0]).tolist(), "delta_pieces": len(self._full[4].breaks) - 1,
            "delta_range": [low, high], "reference": self.reference,
            "estimator_effectivity": [self.estimator(d) / max(t, 1e-300) for d, t in zip(held, truth)],
            "snapshot_s": snapshot_s, "operators_s": operators_s, "build_s": time.perf_counter() - start}

    @classmethod
    def from_sampler(cls, scene, sample, tolerance: float, counts: tuple = (16, 32), **options):
        """Built from ``sample(n)`` (n params dicts, e.g. prior draws) for the first n of ``counts``
        whose model meets ``tolerance``: a basis from too few snapshots misses it
        (``ToleranceMissed``), so the draws grow instead of the build failing; the last count's
        miss is raised. ``options``: the constructor's keywords."""
        if not counts:
            raise ValueError("counts is empty: give the numbers of draws to try, e.g. (16, 32)")
        for count in counts[:-1]:
            try:
                return cls(scene, sample(count), tolerance, **options)
            except ToleranceMissed:
                pass
        return cls(scene, sample(counts[-1]), tolerance, **options)

    def _observed(self, u_free: np.ndarray) -> np.ndarray:
        """The observations (columns, points * dim) of free-dof fields (n_free, columns)."""
        c = self.scene.constraints
        obs0 = self.scene.observe(c.expand(torch.zeros(len(c.free_dofs), dtype=torch.float64))).reshape(-1)
        return torch.sparse.mm(self.scene.observation_matrix(), torch.as_tensor(u_free)).numpy().T + obs0.numpy()

    def _operators(self, V, low, high, max_pieces, thetas) -> tuple:
        """(V, H V, the prescribed dofs' observations, V^T f, blocks(delta), loads(delta))."""
        obs0 = self._observed(np.zeros((V.shape[0], 1)))[0]
        HV = (self._observed(V) - obs0).T
        f = V.T @ self.scene.constraints.free(self.scene.force).numpy()
        blocks, loads = self._delta_pieces(V, HV, f, low, high, max_pieces, thetas)
        return V, torch.as_tensor(HV), torch.as_tensor(obs0), torch.as_tensor(f), blocks, loads

    def _choose_rank(self, held: list[dict], observed: np.ndarray) -> list[float]:
        """The smallest rank whose held-out observation error is within tolerance / 2 (half:
        the held-out draws are few); the errors by rank up to it."""
        errors = []
        for r in range(1, self._full[0].shape[1] + 1):
            self.rank = r
            errors.append(float(np.abs(self._predict_numpy(held) - observed).max()))
            if errors[-1] <= self.tolerance / 2:
                return errors
        raise ToleranceMissed(f"the basis from {self._full[0].shape[1]} snapshots reaches a held-out observation "
                              f"error of {min(errors):.3g} at best, above half the tolerance, {self.tolerance / 2:.3g}: "
                              "give more draws (snapshots), or a larger tolerance")

    def _shape(self, params: dict) -> np.ndarray:
        """The ratios Theta_t / Theta_0: what the solution's shape depends on besides delta
        (its size scales with 1 / Theta_0)."""
        theta = coefficients(self.material, params).numpy()
        return theta[1:] / theta[0]

    def _outside(self, params: dict) -> bool:
        """Whether the moduli's ratios leave the range the snapshots covered (5 % slack)."""
        low, high = self.shape_range
        ratio = self._shape(params)
        return bool(np.any((ratio < low - 0.05 * abs(low)) | (ratio > high + 0.05 * abs(high))))

    def _full_solve(self, params: dict) -> np.ndarray:
        with torch.no_grad():
            return self.scene.factor(params).solve(self.scene.free_load(params).numpy())

    def _projector(self, V):
        """delta -> (V^T A_t V) (T, R, R) and V^T (-A_t u_c) (T, R) at the reference moduli,
        each delta projected once (neighbouring pieces share their ends), B_t V reused where
        B_t's entries do not depend on delta."""
        c = self.scene.constraints
        V_all = np.zeros((c.prescribed.numel(), V.shape[1]))
        V_all[c.free_dofs] = V
        u_c, reuse, done = c.prescribed.reshape(-1).numpy(), {}, {}

        def projected(delta: float):
            if delta not in done:
                terms = Terms(self.material, {**self.reference, "delta": delta})
                done[delta] = terms.project(V_all, u_c, reuse)
            return done[delta]
        return projected

    def _delta_pieces(self, V, HV, f, low, high, max_pieces, thetas):
        """Polynomials in delta on the pieces between the partial volumes' breakpoints, each
        halved until, at its check points, the reduced solutions at the draws' moduli
        (``thetas``: Theta_t / Theta_t(reference) per draw) from the interpolated operators
        match the exactly projected ones' observations to tolerance / 4 (each term's
        interpolation error is scaled by its coefficient, and the ratios spread widely over a
        prior). Returns (blocks, loads) as ``Piecewise``."""
        projected = self._projector(V)

        def observed(S, p):
            return np.stack([HV @ np.linalg.solve(np.tensordot(theta, S, 1), f + theta @ p) for theta in thetas])

        b = breakpoints(self.material.bonds, low, high)
        todo, done, n = list(zip(b[:-1], b[1:])), [], 6
        while todo:
            a, b = todo.pop()
            nodes = [a, *(a + (b - a) * chebyshev_points(n)[1:-1]), b]  # ends exact: shared
            exact = [projected(float(x)) for x in nodes]
            piece = [Piecewise([a, b], [np.stack([e[k] for e in exact])]) for k in (0, 1)]
            worst = max(float(np.abs(observed(*projected(float(x)))
                                         - observed(piece[0](x).numpy(), piece[1](x).numpy())).max())
                        for x in a + (b - a) * check_points(n))
            if worst <= self.tolerance / 4:
                done.append((a, b, exact))
            elif len(todo) + len(done) + 2 > max_pieces:
                raise ToleranceMissed(f"the operators' polynomials in delta reach an observation error of {worst:.3g} "
                                      f"on [{a:.4g}, {b:.4g}] with {max_pieces} pieces, above tolerance/4 = "
                                      f"{self.tolerance / 4:.3g}: raise max_pieces or the tolerance")
            else:
                todo += [(a, 0.5 * (a + b)), (0.5 * (a + b), b)]
        done.sort(key=lambda piece: piece[0])
        breaks = [piece[0] for piece in done] + [done[-1][1]]
        return tuple(Piecewise(breaks, [np.stack([e[k] for e in piece[2]]) for piece in done]) for k in (0, 1))

    @property
    def V(self) -> np.ndarray:
        """The basis (n_free, rank): the first ``rank`` POD vectors (POD bases are nested)."""
        return self._full[0][:, :self.rank]

    def coefficients_of(self, params: dict) -> torch.Tensor:
        """The reduced solution a (rank,) at ``params`` (differentiable)."""
        r = self.rank
        _, _, _, f, blocks, loads = self._full
        q = {k: torch.as_tensor(params[k], dtype=torch.float64) for k in self.param_names}
        theta = coefficients(self.material, q) / self.theta_ref
        K = torch.tensordot(theta, blocks(q["delta"])[:, :r, :r], 1)
        b = f[:r] * torch.as_tensor(params.get("load", 1.0), dtype=torch.float64) \
            + torch.tensordot(theta, loads(q["delta"])[:, :r], 1)
        return torch.linalg.solve(K, b)

    def predict(self, params: dict) -> torch.Tensor:
        """The observations (points, dim) at ``params``, differentiable (twice)."""
        _, HV, obs0, *_ = self._full
        return (HV[:, :self.rank] @ self.coefficients_of(params) + obs0).reshape(self._out_shape)

    def solve(self, params: dict) -> torch.Tensor:
        """The displacement field (N, dim) V a at ``params`` (differentiable)."""
        return self.scene.constraints.expand(torch.as_tensor(self.V) @ self.coefficients_of(params))

    def observe(self, u: torch.Tensor) -> torch.Tensor:
        return self.scene.observe(u)

    def _predict_numpy(self, draws) -> np.ndarray:
        with torch.no_grad():
            return np.stack([self.predict(d).reshape(-1).numpy() for d in draws])

    def error_estimate(self, params: dict) -> float:
        """The estimated largest observation error at ``params`` (``estimator``)."""
        return self.estimator(params)

    def diagnostics(self, draws: dict) -> dict:
        """The error estimate at ``estimates`` evenly spaced draws (arrays (chain, draw); NaN at
        the others; every draw when ``estimates`` is None), with a warning when any exceeds the
        tolerance or lies outside the snapshots' moduli, naming how many."""
        shape = np.shape(next(iter(draws.values())))[:2]
        total = shape[0] * shape[1]
        picks = np.arange(total) if self.estimates is None or self.estimates >= total else \
            np.linspace(0, total - 1, self.estimates).round().astype(int)
        out = np.full(total, np.nan)
        outside = 0
        for i in picks:
            c, d = np.unravel_index(i, shape)
            params = {k: draws[k][c, d] for k in self.param_names}
            out[i] = self.estimator(params)
            outside += self._outside(params)
        if outside:
            warnings.warn(f"{outside} of {len(picks)} draws have moduli whose ratios leave the range of the "
                          f"snapshots ({self.shape_range[0].round(4).tolist()} to {self.shape_range[1].round(4).tolist()}): "
                          "the reduced model extrapolates there; rebuild it with draws that cover them "
                          "(e.g. from a wider prior)", stacklevel=2)
        over = int((out[picks] > self.tolerance).sum())
        if over:
            warnings.warn(f"the reduced model's estimated observation error exceeds its tolerance "
                          f"{self.tolerance:.3g} at {over} of {len(picks)} draws (largest {np.nanmax(out):.3g}): "
                          "rebuild it with draws that cover the posterior (ReducedScene(scene, draws + "
                          "bp.posterior_draws(tree, 20, seed, inflate=4))), or correct the fit with the "
                          "full model (importance_correction)", stacklevel=2)
        return {"reduced_error_estimate": out.reshape(shape)}
