"""The dynamic MD fracture records (experiments/md_graphene_data.py) as PD forward problems on a
coarse grid, and the paper's metrics of a forward run (paper 004 sec. 5.2-5.3): an example scene
(``bayespd.scenes.md_fracture``); experiments/md_learning.py runs it and writes the metrics.

Scene: the coarse grid's nodes (spacing h, cells h^2, unit thickness), the learned LPS at delta,
the 25 A edge slit cut as a pre-crack along the removed atom column's centre line
(``bayespd.learn.md_damage.slit_centre``), the coarse-grained MD density of frame 0. Fracture run:
the outermost node column on each side follows the coarse-grained MD displacement (linear in
time between frames; the gripped atoms lie beyond the grid), the other nodes start on the MD
run's initial velocity field v_x = v0 (1/2 - y / L) clip(x / (W/2), -1, 1)
(``bayespd.learn.md.fracture_run``). Pulse run: free edges, at rest, the coarse-grained pulse
body force (linear in time between frames). ``surface=True``: the free-surface-corrected LPS of
paper 004 eq 3.18 (``bayespd.learn.free_surface``) with the missing bonds beyond the free edges and
across the slit as broken bonds; the sites beyond the pulled columns (where the grips are) are the
paper's Dirichlet collar, moving with their nearest node.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass

import numpy as np
import torch

from bayespd.bonds import crossing, find_bonds
from bayespd.damage import DamageIndex
from bayespd.discretize import from_points
from bayespd.infer.calibration import interval_score
from bayespd.influence import Bernstein
from bayespd.learn.crack_length import fitted_errors, forecast, length_resolution, log_evidence
from bayespd.learn.damage_error import cone_average, lagged, shifted, straight_crack_intact
from bayespd.learn.discrepancy import count_damage, relative_error, relative_mse
from bayespd.learn.forward import ETA_OVER_S0, forward_run, forward_runs, linear_in_time
from bayespd.learn.kernel import lps_params
from bayespd.learn.model_error import fit_relative_error
from bayespd.learn.md_damage import broken_atom_bonds, cut_coarse_bonds, slit_centre, tip_height
from bayespd.materials.lps import LPS

DEGREE = 3
SLIT_TIP = -25.0  # A: the top of the 25 A edge slit; crack lengths are measured from here


@dataclass
class Scene:
    material: object
    params: dict
    rho: np.ndarray
    time: np.ndarray
    u: np.ndarray            # coarse MD displacement (F, N, 2)
    phi: np.ndarray          # coarse MD damage index (F, N)
    intact: np.ndarray       # MD intact fraction (0/1) of the coarse bonds (F, bonds)
    tip: np.ndarray          # MD crack tip height per frame (A; NaN before the first break)
    fixed: np.ndarray
    slit_x: float            # A: the pre-crack's line (``slit_centre``)
    slit_bonds: object       # the bonds the pre-crack removed (``bayespd.bonds.Bonds``)
    moving: object
    v0: np.ndarray
    body: object
    surface: object = False  # forward_run's: False, True or free(sites) -> bool

    def run(self, s0, frames=None, eta_over_s0=ETA_OVER_S0):
        """A forward run over the first ``frames`` frames (all: None), eq 3.10's width eta_over_s0 s0."""
        t = self.time if frames is None else self.time[:frames]
        return forward_run(self.material, self.params, self.rho, t, s0, self.fixed, self.moving, self.v0, self.body,
                           surface=self.surface, eta_over_s0=eta_over_s0)

    def runs(self, s0s, eta_over_s0s) -> list:
        """Full-record runs at each pair (s0, eta / s0), batched (``forward_runs``)."""
        return forward_runs(self.material, self.params, self.rho, self.time, s0s, eta_over_s0s, self.fixed,
                            self.moving, self.v0, self.body, surface=self.surface)


def scene(coarse, record, kernel: dict, h: float, pulled: bool, surface: bool = False) -> Scene:
    """The forward problem of a coarse record (``coarse``: the npz of the coarse graining; ``record``:
    the atom record) with ``kernel`` = {lambda, mu, D, delta_A}; ``surface``: eq 3.18 (module docstring)."""
    x = coarse["nodes"]
    particles = from_points(x, np.full(len(x), h * h), h=h)
    delta = kernel["delta_A"]
    X, t, u = record["X"].values, coarse["time"], coarse["u"]
    centre = slit_centre(X, SLIT_TIP)  # the removed atom column (x = -0.62 A in the records)
    slit = [[centre, x[:, 1].min() - h], [centre, SLIT_TIP]]
    bonds = find_bonds(particles, delta)
    cut = crossing(particles, bonds, slit)
    material = LPS(particles, bonds.without(cut), plane="strain", influence=Bernstein(DEGREE))
    params = lps_params(kernel["lambda"], kernel["mu"], kernel["D"], delta)
    pairs, broken = broken_atom_bonds(X, record["U"].values)
    intact = cut_coarse_bonds(x, material.bonds.i, material.bonds.j, X, pairs, broken)
    index = DamageIndex(particles, material.bonds, material.bond_weight(params).detach())
    phi = np.stack([index(torch.as_tensor(g)).numpy() for g in intact])
    tip = tip_height(0.5 * (X[pairs[:, 0], 1] + X[pairs[:, 1], 1]), broken)
    v0 = np.zeros_like(x)
    if pulled:
        fixed = np.abs(x[:, 0]) >= np.abs(x[:, 0]).max() - h / 2
        speed = json.loads(record.attrs["settings"])["v0"]
        length, half_width = np.ptp(X[:, 1]), np.ptp(X[:, 0]) / 2
        v0[:, 0] = speed * (0.5 - x[:, 1] / length) * np.clip(x[:, 0] / half_width, -1.0, 1.0)
        lo, hi = x[:, 0].min() - h / 2, x[:, 0].max() + h / 2
        free = (lambda sites: (sites[:, 0] > lo) & (sites[:, 0] < hi)) if surface else False  # beyond the pulled columns: collar
        return Scene(material, params, coarse["rho"][0], t, u, phi, intact, tip, fixed, centre, bonds.without(~cut),
                     linear_in_time(t, u), v0, None, free)
    return Scene(material, params, coarse["rho"][0], t, u, phi, intact, tip, np.zeros(len(x), bool), centre,
                 bonds.without(~cut), None, v0, linear_in_time(t, coarse["b"]), surface)


def crack_history(time_ps, tip, still: float = 2.5, after: int = 3) -> dict:
    """Crack length (tip - SLIT_TIP, 0 before initiation) per frame; initiation time (first frame
    with a broken bond); arrest: the first frame after which the crack grows by less than ``still``
    A to the end of the record, if at least ``after`` frames follow it (else None: still running);
    mean running speed from initiation to arrest (or the last frame), A/ps."""
    length = np.where(np.isnan(tip), 0.0, np.maximum(tip - SLIT_TIP, 0.0))
    grown = np.flatnonzero(~np.isnan(tip))
    out = {"length_A": length.tolist(), "final_length_A": float(length[-1])}
    if grown.size == 0:
        return {**out, "initiation_ps": None, "arrest_ps": None, "speed_A_per_ps": None}
    start = int(grown[0])
    stop = int(np.flatnonzero(length[-1] - length < still)[0])
    arrested = stop <= len(length) - 1 - after
    end = stop if arrested else len(length) - 1
    speed = (length[end] - length[start]) / (time_ps[end] - time_ps[start]) if end > start else 0.0
    return {**out, "initiation_ps": float(time_ps[start]), "arrest_ps": float(time_ps[stop]) if arrested else None,
            "speed_A_per_ps": float(speed)}


def metrics(sc: Scene, run, frames=slice(None)) -> dict:
    """The paper's errors of a forward run over ``frames`` (bayespd.learn.discrepancy): displacement
    (free nodes) and damage (all nodes), ``*_rel_error`` (norm ratio) and ``*_rel_mse`` (its square,
    the paper's words read literally); damage of the kernel-weighted index (``damage_*``) and of
    the paper's eq 5.4 count (``damage_eq54_*``), the latter the one the targets use; and eq 5.4 as
    printed, over every x_j in B_delta with the slit's bonds as broken (``damage_eq54_with_slit_*``:
    the slit then counts in both fields, and in every frame)."""
    free = ~sc.fixed
    u, u_md = run.u[frames], sc.u[frames]
    out = {"displacement_rel_error": relative_error(u, u_md, free), "displacement_rel_mse": relative_mse(u, u_md, free)}
    b, s = sc.material.bonds, sc.slit_bonds

    def eq54(cut=None):
        return [count_damage(len(free), b.i, b.j, b.length, float(sc.params["delta"]), g[frames], cut)
                for g in (run.intact, sc.intact)]
    readings = {"damage": (run.phi[frames], sc.phi[frames]), "damage_eq54": eq54(),
                "damage_eq54_with_slit": eq54((s.i, s.j, s.length))}
    for name, (pred, data) in readings.items():
        try:
            out[f"{name}_rel_error"], out[f"{name}_rel_mse"] = relative_error(pred, data), relative_mse(pred, data)
        except ValueError:  # no MD damage in these frames
            out[f"{name}_rel_error"] = out[f"{name}_rel_mse"] = None
    return out


def damage_diagnosis(sc: Scene, run, frames=slice(None), lags=range(-3, 4), shifts=(-2, -1, 1, 2)) -> dict:
    """Where the eq 5.4 damage error (norm reading) of ``run`` over ``frames`` comes from
    (``bayespd.learn.damage_error``): the error with the PD history lagged by whole frames
    (timing), with the PD field moved by whole grid columns (crack line), with both fields
    cone-averaged over the horizon (the same operator on both: paths closer than delta agree), of
    a straight crack along the slit line with the MD tip history (the MD timing and length
    exactly: the part due to the MD path alone), and of the PD run against that straight crack; the
    straight crack's also with the slit's bonds counted (``metrics``' ``damage_eq54_with_slit``), over
    ``frames`` and over the whole record."""
    x, b, s = sc.material.particles.x, sc.material.bonds, sc.slit_bonds
    delta = float(sc.params["delta"])

    def eq54(intact, cut=None):
        return count_damage(len(x), b.i, b.j, b.length, delta, intact, cut)

    def error(pred, data, over=frames):
        return relative_error(pred[over], data[over])

    pd, md = eq54(run.intact), eq54(sc.intact)
    by_lag = {int(k): error(lagged(pd, k), md) for k in lags}
    by_shift = {float(c * b.h): error(shifted(pd, x, [c * b.h, 0.0]), md) for c in shifts}
    straight_intact = straight_crack_intact(x, b.i, b.j, sc.slit_x, SLIT_TIP, sc.tip)
    straight = eq54(straight_intact)
    slit = (s.i, s.j, s.length)
    with_slit = eq54(straight_intact, slit), eq54(sc.intact, slit)
    lag, shift = min(by_lag, key=by_lag.get), min(by_shift, key=by_shift.get)
    return {"as_run": error(pd, md), "by_lag_frames": by_lag, "best_lag_frames": lag, "at_best_lag": by_lag[lag],
            "by_shift_A": by_shift, "best_shift_A": shift, "at_best_shift": by_shift[shift],
            "both_cone_averaged_over_delta": error(cone_average(pd, x, delta), cone_average(md, x, delta)),
            "straight_crack_md_tip_vs_md": error(straight, md), "pd_vs_straight_crack_md_tip": error(pd, straight),
            "straight_crack_md_tip_vs_md_with_slit": error(*with_slit),
            "straight_crack_md_tip_vs_md_with_slit_whole_record": error(*with_slit, over=slice(None))}


def displacement_diagnosis(sc: Scene, run) -> dict:
    """Where a run's displacement error on the free nodes comes from, per frame from frame 1: MD's
    field as a multiple of the run's, a_t = <u_md, u_pd> / <u_pd, u_pd> (a sheet more compliant than
    the model's, > 1); the relative error |u_pd - u_md| / |u_md| of the nodes within delta of the
    slit line and of the others; and that of a_t u_pd (what is left when the
    amplitude is right)."""
    free = ~sc.fixed
    x = sc.material.particles.x[free]
    band = np.abs(x[:, 0] - sc.slit_x) <= float(sc.params["delta"])
    u, u_md = run.u[1:, free], sc.u[1:, free]
    factor = np.einsum("fnc,fnc->f", u_md, u) / np.einsum("fnc,fnc->f", u, u)

    def error(pred, nodes=slice(None)):
        return (np.linalg.norm((pred - u_md)[:, nodes], axis=(1, 2)) / np.linalg.norm(u_md[:, nodes], axis=(1, 2))).tolist()
    return {"md_over_pd_factor": factor.tolist(), "rel_error_near_slit_line": error(u, band),
            "rel_error_elsewhere": error(u, ~band), "rel_error_after_factor": error(factor[:, None, None] * u)}


def pd_tip(sc: Scene, run) -> np.ndarray:
    """PD crack tip height per frame: the highest midpoint of the bonds with gamma < 1/2."""
    x, b = sc.material.particles.x, sc.material.bonds
    return tip_height(0.5 * (x[b.i, 1] + x[b.j, 1]), run.intact < 0.5)


def evaluate(sc: Scene, s0, frames=slice(None)) -> dict:
    """One full forward run at ``s0``: errors over ``frames`` and the whole record, crack histories."""
    t = time.perf_counter()
    run = sc.run(s0)
    wall = time.perf_counter() - t
    return {"s0": s0, "wall_time_s": wall, "steps": run.steps, "dt_ps": run.dt, "frames": metrics(sc, run, frames),
            "whole_record": metrics(sc, run), "damage_diagnosis": damage_diagnosis(sc, run, frames),
            "displacement_diagnosis": displacement_diagnosis(sc, run),
            "crack_pd": crack_history(sc.time, pd_tip(sc, run)),
            "crack_md": crack_history(sc.time, sc.tip)}


NOISE_MODELS = ("iid", "per_frame", "relative_iid", "relative_per_frame", "relative_growing", "relative_correlated")
GROWTH = np.linspace(0.0, 3.0, 61)  # "relative_growing"'s exponents gamma: sd r s_t (t / t_fit)^gamma
WIDTHS = np.geomspace(0.05, 0.8, 5)  # eq 3.10's eta / s0 on the grid: near the sharp law to a wide softening
ALPHA = 0.1  # the bands' level: central 90 % intervals


def damage_posterior(sc: Scene, half: int, bounds, draws: int = 200, seed: int = 0, widths=WIDTHS,
                     others: dict | None = None) -> dict:
    """Grid posteriors of eq 3.10's (log s0, log eta / s0) from the training frames' displacements,
    under six noise models, and their crack lengths; 90 % predictive bands for frames half .. end
    and of the crack-length history; the noise model chosen by leave-future-out on the training frames.

    Likelihood: the displacements and the crack lengths, independent given (s0, eta). Displacements:
    u_md = u_pd + e on the free nodes of the fitted frames, e Gaussian with sigma marginalised under
    p(sigma) ~ 1/sigma: p(data | s0, eta) ~ SSE^(-n/2); prior uniform in log s0 and log eta / s0.
    Two readings of n: every nodal value independent ("iid", n = 2 x nodes x frames: ignores the
    correlation of model error over space, so too narrow) and one independent value per frame
    ("per_frame", n = frames: the error field of a frame moves as one). "relative_*": the same with
    e's sd r s_t relative to the frame's rms PD displacement s_t (the error grows with the field):
    p ~ SSE_rel^(-n/2) prod_t s_t^(-n / frames), SSE_rel = sum_t |e_t|^2 / s_t^2.
    "relative_growing": relative iid with s_t times (t / t_fit)^gamma, t_fit the last fitted frame's
    time, gamma on ``GROWTH`` (uniform prior; gamma = 0 is "relative_iid"): the relative error itself
    grows over the training frames (5 % of the field at the first, 20-25 % later: model_error's
    docstring), which a constant r carries into the extrapolation at its training average.
    "relative_correlated": ``bayespd.learn.model_error``'s term (``_relative_correlated``). Crack
    lengths: MD's minus the run's from the frame before MD's first break, iid with their scale
    marginalised above the half-step resolution (``bayespd.learn.crack_length``): eta sets how
    fast a PD crack runs, which the displacements barely see (docs/results.md, issue 28, stop 46).
    Grid: 61 s0 evenly in log over the prior's ``bounds`` times ``widths``, one full-record run
    each; the fits to all training frames, narrower than the coarse step, then on a grid zoomed to
    where the models' mass lies (``_zoom``: 61 s0 over the coarse range holding
    all but 1e-3 of each, a coarse step wider; the mass left out reported). Predictive: ``draws``
    (s0, eta) from the grid weights, each run plus its noise per value (sd sigma, or r s_t of the
    predicted frame), and its crack lengths plus a draw of their error.

    Choice (``chosen``): each model fitted to frames 1 .. half / 2 - 1 predicts frames half / 2 ..
    half - 1 (the training frames only; they hold the crack's initiation), scored by the mean
    interval score of its 90 % displacement bands over those values (Gneiting & Raftery 2007 eq 43:
    width plus 2 / alpha times the miss, a proper score of the interval); the lowest is the model
    the bands are reported with (Buerkner, Gabry & Vehtari 2020's leave-future-out, one split).

    ``others``: {test: (scene, s0 scale)}: each model's draws predict the whole record of another
    scene (the paper's tests (ii), (iii): another load, another grid with s0 scaled), their runs
    there plus their noise (``_elsewhere``): the share of its MD node-frames inside the bands, and
    the runs' crack histories against MD's."""
    s0s = np.exp(np.linspace(np.log(bounds[0]), np.log(bounds[1]), 61))
    widths = np.asarray(widths, float)
    runs, crack = _grid_runs(sc, s0s, widths)
    cut = half // 2
    held = {name: _predictive(sc, runs, crack, name, cut, slice(cut, half), draws, seed) for name in NOISE_MODELS}
    scores = {name: interval_score(p.pred, p.data, 1 - ALPHA) for name, p in held.items()}
    coarse = {name: _predictive(sc, runs, crack, name, half, slice(half, None), 1, seed).weights  # the weights only
              .reshape(len(s0s), -1).sum(1) for name in NOISE_MODELS}
    s0s, neglected = _zoom(s0s, coarse)
    runs, crack = _grid_runs(sc, s0s, widths)
    fits = {name: _predictive(sc, runs, crack, name, half, slice(half, None), draws, seed) for name in NOISE_MODELS}
    grid = (np.repeat(s0s, len(widths)), np.tile(widths, len(s0s)))
    elsewhere = {test: _elsewhere(other, scale, grid, fits, sc.time[half - 1], np.random.default_rng(seed + 2))
                 for test, (other, scale) in (others or {}).items()}
    out = {}
    for name, fit in fits.items():
        lo, hi = np.quantile(held[name].pred, [ALPHA / 2, 1 - ALPHA / 2], axis=0)
        out[name] = {**fit.fitted, "leave_future_out_interval_score_A": scores[name],
                     "leave_future_out_band90_node_frame_coverage": float(_inside(held[name].data, lo, hi).mean()),
                     **_marginals(fit.weights.reshape(len(s0s), len(widths)), s0s, widths),
                     **_bands(fit.pick, fit.pred, fit.data, crack, half, np.random.default_rng(seed + 1)),
                     **{test: carried[name] for test, carried in elsewhere.items()}}
    free = ~sc.fixed
    sse = np.array([((r.u[1:half, free] - sc.u[1:half, free]) ** 2).sum() for r in runs])
    return {"s0_grid": s0s.tolist(), "eta_over_s0_grid": widths.tolist(), "coarse_mass_left_out": neglected,
            "training_sse_A2": sse.tolist(),
            "crack_length_log_evidence": [crack.log_evidence(k, half) for k in range(len(runs))],
            "leave_future_out_frames": [cut, half], "chosen": min(scores, key=scores.get), **out}


def _grid_runs(sc: Scene, s0s, widths):
    """A full-record run at every (s0, eta / s0) of the grid (s0 major), and their crack lengths."""
    runs = sc.runs(np.repeat(s0s, len(widths)), np.tile(widths, len(s0s)))
    md = np.asarray(crack_history(sc.time, sc.tip)["length_A"])
    lengths = np.array([crack_history(sc.time, pd_tip(sc, r))["length_A"] for r in runs])
    return runs, _CrackLengths(sc.time, md, lengths, int(np.flatnonzero(md > 0)[0]), length_resolution(sc.material.bonds.h))


def _zoom(s0s, weights: dict, left_out: float = 1e-3):
    """61 s0 evenly in log over the smallest coarse range that holds all but ``left_out`` of every
    model's marginal (``weights``: name -> (s0s,); half of it each side), a coarse step wider each
    side; and the largest mass left out."""
    cdfs = [np.cumsum(w) for w in weights.values()]
    a = max(min(int(np.searchsorted(c, left_out / 2)) for c in cdfs) - 1, 0)
    b = min(max(int(np.searchsorted(c, 1 - left_out / 2)) for c in cdfs) + 1, len(s0s) - 1)
    lost = max(float(w[:a].sum() + w[b + 1:].sum()) for w in weights.values())
    return np.exp(np.linspace(np.log(s0s[a]), np.log(s0s[b]), len(s0s))), lost


@dataclass
class _CrackLengths:
    """The frame times (F,), MD's crack lengths (F,), the grid runs' (runs, F), MD's first cracked
    frame and the resolution q (``bayespd.learn.crack_length``)."""
    time: np.ndarray
    md: np.ndarray
    runs: np.ndarray
    first: int
    q: float

    def log_evidence(self, k: int, end: int) -> float:
        """Of run k's lengths given frames to end - 1."""
        return log_evidence(fitted_errors(self.md, self.runs[k], self.first, end), self.q)

    def history(self, lengths) -> dict:
        """``crack_history`` of a length history (F,)."""
        return crack_history(self.time, np.where(lengths > 0, SLIT_TIP + lengths, np.nan))

    def forecast(self, rng, k: int, end: int) -> np.ndarray:
        """A draw of MD's lengths from frame ``end`` on given run k and the frames before."""
        return forecast(rng, self.md, self.runs[k], self.first, end, self.q)


@dataclass
class _Prediction:
    """A noise model fitted to the training frames: the grid weights, the draws' grid points, their
    predictive draws (draws, frames, free nodes, 2) and the MD data there, the fit's numbers, and
    each draw's error level (sd in A; for ``relative`` models relative to a frame's rms PD
    displacement, times (t / t_fit)^growth)."""
    weights: np.ndarray
    pick: np.ndarray
    pred: np.ndarray
    data: np.ndarray
    fitted: dict
    level: np.ndarray
    growth: np.ndarray
    relative: bool


def _predictive(sc: Scene, runs, crack: _CrackLengths, name: str, end: int, late: slice, draws: int, seed: int):
    """Noise model ``name`` fitted to frames 1 .. end - 1 predicting frames ``late`` (a ``_Prediction``;
    ``damage_posterior``'s docstring)."""
    free = ~sc.fixed
    crack_logp = np.array([crack.log_evidence(k, end) for k in range(len(runs))])
    if name == "relative_correlated":
        return _relative_correlated(sc, runs, crack_logp, end, late, draws, seed)
    relative, per_frame = name.startswith("relative"), name.endswith("per_frame")
    growth = GROWTH if name == "relative_growing" else np.zeros(1)
    residuals = [r.u[1:end, free] - sc.u[1:end, free] for r in runs]
    values = residuals[0].size
    n = end - 1 if per_frame else values
    t = sc.time
    if relative:  # s_t g_t per (grid, growth, frame): rms PD displacement times (t / t_fit)^gamma
        rms = np.array([np.sqrt((r.u[1:end, free] ** 2).mean((1, 2))) for r in runs])
        s = rms[:, None, :] * (t[1:end] / t[end - 1])[None, None, :] ** growth[None, :, None]
    else:
        s = np.ones((len(runs), 1, end - 1))
    sse = np.array([[((e / sg[:, None, None]) ** 2).sum() for sg in sk] for e, sk in zip(residuals, s)])
    logp = -0.5 * n * np.log(sse / sse.min()) - n / (end - 1) * np.log(s).sum(-1) + crack_logp[:, None]  # (grid, growth)
    joint = np.exp(logp - logp.max()).ravel()
    joint /= joint.sum()
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(joint), size=draws, p=joint)
    pick, shape = chosen // len(growth), chosen % len(growth)
    level, gamma = np.sqrt(sse[pick, shape] / values), growth[shape]
    data = sc.u[late][:, free]
    pred = _draws((runs[k].u[late][:, free] for k in pick), t[late], level, gamma, relative, t[end - 1], rng)
    fitted = {"n": int(n)}
    if len(growth) > 1:
        fitted["growth_exponent_posterior"] = dict(zip(growth.tolist(), joint.reshape(len(runs), -1).sum(0).tolist()))
    return _Prediction(joint.reshape(len(runs), -1).sum(1), pick, pred, data, fitted, level, gamma, relative)


def _draws(runs_u, times, level, growth, relative: bool, t_fit: float, rng) -> np.ndarray:
    """Predictive draws: each run's displacements u (F, n, 2) at ``times`` plus an independent
    error per value of sd ``level`` (A), or for ``relative`` models ``level`` times the frame's rms
    of u times (t / t_fit)^growth."""
    def sd(u, a, g):
        if not relative:
            return np.full((len(u), 1, 1), a)
        return a * (np.sqrt((u**2).mean((1, 2))) * (times / t_fit) ** g)[:, None, None]
    return np.stack([u + sd(u, a, g) * rng.standard_normal(u.shape) for u, a, g in zip(runs_u, level, growth)])


def _elsewhere(other: Scene, scale: float, grid, fits: dict, t_fit: float, rng) -> dict:
    """Per noise model, its draws carried to ``other``: each drawn grid point's run of ``other`` (s0
    times ``scale``, the same eta / s0) plus an error of the draw's level (its marginal sd: the
    correlated model's spatial correlation leaves each value's band as it is); the share of the
    MD node-frames (free nodes, frames 1 on) inside their 90 % bands, and the runs' crack histories
    against MD's (``_history_intervals``)."""
    s0s, widths = grid
    points = np.unique(np.concatenate([fit.pick for fit in fits.values()]))
    runs = dict(zip(points, other.runs(s0s[points] * scale, widths[points])))
    histories = {k: crack_history(other.time, pd_tip(other, run)) for k, run in runs.items()}
    md = crack_history(other.time, other.tip)
    free, t = ~other.fixed, other.time[1:]
    data = other.u[1:, free]
    out = {}
    for name, fit in fits.items():
        pred = _draws((runs[k].u[1:, free] for k in fit.pick), t, fit.level, fit.growth, fit.relative, t_fit, rng)
        lo, hi = np.quantile(pred, [ALPHA / 2, 1 - ALPHA / 2], axis=0)
        out[name] = {"band90_node_frame_coverage": float(_inside(data, lo, hi).mean()),
                     **_history_intervals([histories[k] for k in fit.pick], md)}
    return out


def _relative_correlated(sc: Scene, runs, crack_logp, end: int, late: slice, draws: int, seed: int):
    """``_predictive`` for ``bayespd.learn.model_error``'s term: error relative to each frame's rms
    PD displacement s_t, exponentially correlated in space and time, (ell, tau) by evidence at the
    best-fitting grid point on grids (h/2 .. 64 h, half a frame .. 32 frames), r marginalised;
    ``crack_logp`` the crack-length log evidences."""
    free = ~sc.fixed
    train = slice(1, end)
    x, t = sc.material.particles.x[free], sc.time[train]
    residuals = [sc.u[train][:, free] - r.u[train][:, free] for r in runs]
    scales = [np.sqrt((r.u[train][:, free] ** 2).mean((1, 2))) for r in runs]
    best = int(np.argmin([((e / s[:, None, None]) ** 2).sum() for e, s in zip(residuals, scales)]))
    h, step = sc.material.bonds.h, float(np.diff(sc.time).mean())
    term, table = fit_relative_error(residuals[best], scales[best], x, t, h * 2.0 ** np.arange(-1, 7),
                                     step * 2.0 ** np.arange(-1, 6))
    logp = np.array([term.log_evidence(e, s) for e, s in zip(residuals, scales)]) + crack_logp
    w = np.exp(logp - logp.max())
    w /= w.sum()
    values = residuals[0].size
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(runs), size=draws, p=w)
    pred, level = [], []
    for k in pick:
        u = runs[k].u[late][:, free]
        level.append(np.sqrt(term.quadratic(residuals[k], scales[k]) / rng.chisquare(values)))
        pred.append(u + term.draw(rng, np.sqrt((u**2).mean((1, 2))), level[-1], 2))
    fitted = {"ell_A": term.ell, "tau_ps": term.tau, "log_evidence_ell_by_tau": table.tolist(),
              "r_at_best": float(np.sqrt(term.quadratic(residuals[best], scales[best]) / values))}
    return _Prediction(w, pick, np.stack(pred), sc.u[late][:, free], fitted, np.array(level), np.zeros(draws), True)


def _inside(data, lo, hi) -> np.ndarray:
    """Per node and frame: both components inside their bands."""
    return ((data >= lo) & (data <= hi)).all(-1)


def _marginals(w, s0s, widths) -> dict:
    """s0's quantiles and eta / s0's weights from the grid weights ``w`` (s0s, widths)."""
    cdf = np.cumsum(w.sum(1))
    return {"s0_q05": float(s0s[np.searchsorted(cdf, 0.05)]), "s0_median": float(s0s[np.searchsorted(cdf, 0.5)]),
            "s0_q95": float(s0s[np.searchsorted(cdf, 0.95)]), "eta_over_s0_weights": w.sum(0).tolist(),
            "weight_at_s0_grid_ends": float(w[0].sum() + w[-1].sum())}


def _bands(pick, pred, data, crack: _CrackLengths, half: int, rng) -> dict:
    """The 90 % bands of the predictions ``pred`` (draws at the grid points ``pick``) and of the crack
    lengths of frames ``half`` on (the runs' at ``pick`` plus their error fitted on frames to
    half - 1, ``bayespd.learn.crack_length``; and the runs' alone), with the share of the MD data
    inside; and the drawn runs' crack histories (``_history_intervals``)."""
    lo, hi = np.quantile(pred, [ALPHA / 2, 1 - ALPHA / 2], axis=0)
    lengths = np.stack([crack.forecast(rng, k, half) for k in pick])
    out = {"extrapolation_band90_node_frame_coverage": float(_inside(data, lo, hi).mean())}
    for name, drawn in (("crack_length", lengths), ("crack_length_runs_only", crack.runs[pick, half:])):
        c_lo, c_hi = np.quantile(drawn, [ALPHA / 2, 1 - ALPHA / 2], axis=0)
        inside = (crack.md[half:] >= c_lo) & (crack.md[half:] <= c_hi)
        out |= {f"{name}_band90_A": {"q05": c_lo.tolist(), "q95": c_hi.tolist()},
                f"{name}_md_inside_band_share_of_forecast_frames": float(inside.mean())}
    return out | _history_intervals([crack.history(crack.runs[k]) for k in pick], crack.history(crack.md))


def _history_intervals(histories: list, md: dict) -> dict:
    """Of drawn runs' ``crack_history``s: 90 % intervals of the initiation time and running speed
    (MD's inside?), the share that arrest and the 90 % interval of their arrest times."""
    out = {}
    for key in ("initiation_ps", "speed_A_per_ps"):
        values = [h[key] for h in histories if h[key] is not None]
        q05, q95 = np.quantile(values, [ALPHA / 2, 1 - ALPHA / 2]).tolist() if values else (None, None)
        out[f"crack_{key}"] = {"q05": q05, "q95": q95, "md": md[key], "runs_without_crack": len(histories) - len(values),
                               "md_inside": bool(values) and md[key] is not None and q05 <= md[key] <= q95}
    arrests = [h["arrest_ps"] for h in histories if h["arrest_ps"] is not None]
    q05, q95 = np.quantile(arrests, [ALPHA / 2, 1 - ALPHA / 2]).tolist() if arrests else (None, None)
    out["crack_arrest"] = {"share_of_runs_arrested": len(arrests) / len(histories), "md_arrest_ps": md["arrest_ps"],
                           "arrested_q05_ps": q05, "arrested_q95_ps": q95,
                           "md_inside": bool(arrests) and md["arrest_ps"] is not None and q05 <= md["arrest_ps"] <= q95}
    return out
