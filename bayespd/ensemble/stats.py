"""Aggregate crack-ensemble realisations into one ``xarray.Dataset``.

Per realisation (dim ``realisation``, labelled by ``ensemble`` and ``index``): the damage
index phi (Dodwell 2019 eq 5's damage summed per particle), crack path, the time series of the run,
the crack length at the end of each load step, the path's offset across the expected crack
line at ``station``s along it, the scalar outcomes and the inputs (parameters, draw, seed).

Summaries per ensemble (dim ``kind``: posterior, mean): the damage-probability map
``probability`` = P(phi > threshold); the 5/50/95 % quantiles of the path offset per station
(the credible band, over the realisations whose path reaches the station, ``path_coverage``)
and of each outcome; and ``spread`` (outcome, source): the standard deviation of the posterior
ensemble (total), of the mean ensemble (aleatoric: Brownian only), and epistemic =
sqrt(max(0, total^2 - aleatoric^2)) by the law of total variance,
Var Y = E[Var(Y | params)] + Var(E[Y | params]), with E[Var(Y | params)] read at the
posterior mean (exact when the Brownian spread does not vary over the posterior).
"""
from __future__ import annotations

import numpy as np
import xarray as xr

QUANTILES = (0.05, 0.5, 0.95)
OUTCOMES = ("failure_load_factor", "peak_load", "peak_load_factor", "final_crack_length", "first_failure_time")
KINDS = ("posterior", "mean")
TIMES = ("wall_time_s", "cpu_time_s")  # per realisation; differ between runs of the same plan


def quantiles(values) -> np.ndarray:
    """5/50/95 % quantiles of the finite values (NaN where there are none)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return np.quantile(v, QUANTILES) if len(v) else np.full(len(QUANTILES), np.nan)


def sd(values) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.std(ddof=1)) if len(v) > 1 else np.nan


def _finite_mean(values) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else np.nan


def padded(arrays, fill=np.nan, dtype=np.float64) -> np.ndarray:
    """Stack arrays of different first lengths, padding with ``fill``."""
    n = max([len(a) for a in arrays] + [1])
    shape = next((np.shape(a)[1:] for a in arrays if len(a)), np.shape(arrays[0])[1:])
    out = np.full((len(arrays), n, *shape), fill, dtype=dtype)
    for i, a in enumerate(arrays):
        out[i, :len(a)] = a
    return out


def offsets(path, origin, direction, stations) -> np.ndarray:
    """Offset of a path across the line origin + s direction at each station s (NaN beyond
    the path's extent along the line)."""
    if len(path) < 2:
        return np.full(len(stations), np.nan)
    d = np.asarray(direction)
    rel = np.asarray(path) - origin
    s, o = rel @ d, rel @ np.array([-d[1], d[0]])
    order = np.argsort(s, kind="stable")
    s, o = s[order], o[order]
    out = np.interp(stations, s, o)
    out[(stations < s[0]) | (stations > s[-1])] = np.nan
    return out


def load_step_lengths(load_factor, crack_length, load_factors) -> np.ndarray:
    """Crack length at the end of each load step (the last step at that load factor; with
    ``hold`` a factor is repeated while bonds break). NaN for steps the run never reached."""
    out = np.full(len(load_factors), np.nan)
    for k, lam in enumerate(load_factors):
        at = np.flatnonzero(load_factor == lam)
        if len(at):
            out[k] = crack_length[at[-1]]
    return out


def stations_for(scene, paths, count: int = 61) -> np.ndarray:
    """``count`` stations spanning the paths' extent along the crack direction."""
    rel = [np.asarray(p) - scene.origin for p in paths if len(p) >= 2]
    if not rel:
        return np.zeros(1)
    s = np.concatenate([r @ np.asarray(scene.direction) for r in rel])
    return np.linspace(s.min(), s.max(), count)


def aggregate(results, scene, seed: int) -> xr.Dataset:
    """``results``: (kind, i, result, params, draw, brownian seed) per realisation, ``result``
    from ``scene.realise`` or ``{"error": message}`` (kept as a failed realisation)."""
    ok = [r for r in results if "error" not in r[2]]
    if not ok:
        raise ValueError("every realisation failed (see the .err.json files in the store): "
                         "reduce dt or the noise of the scene")
    n_particles = len(scene.x)
    for r in ok:
        if r[2]["phi"].shape != (n_particles,):
            raise ValueError(f"a realisation has {r[2]['phi'].shape[0]} particles, the scene's x "
                             f"{n_particles}: give the scene the positions of the body build makes")
    res = [r[2] for r in ok]
    stations = stations_for(scene, [r["path"] for r in res])
    kind = np.array([r[0] for r in ok])
    per = {
        "phi": (("realisation", "particle"), np.stack([r["phi"] for r in res])),
        "path": (("realisation", "point", "component"), padded([r["path"] for r in res])),
        "t": (("realisation", "step"), padded([r["t"] for r in res])),
        "load_factor": (("realisation", "step"), padded([r["load_factor"] for r in res])),
        "reaction": (("realisation", "step", "component"), padded([r["reaction"] for r in res])),
        "broken": (("realisation", "step"), padded([r["broken"] for r in res], -1, np.int64)),
        "crack_length": (("realisation", "step"), padded([r["crack_length"] for r in res])),
        "crack_length_at_load": (("realisation", "load_step"), np.stack(
            [load_step_lengths(r["load_factor"], r["crack_length"], scene.load_factors) for r in res])),
        "offset": (("realisation", "station"), np.stack(
            [offsets(r["path"], scene.origin, scene.direction, stations) for r in res])),
        **{k: ("realisation", np.array([float(r[k]) for r in res])) for k in OUTCOMES},
        **{k: ("realisation", np.array([float(r.get(k, np.nan)) for r in res])) for k in TIMES},
        **{f"param_{k}": ("realisation", np.array([r[3][k] for r in ok])) for k in scene.params},
        "draw": ("realisation", np.array([r[4] for r in ok], dtype=np.int64)),
        "brownian_seed": ("realisation", np.array([r[5] for r in ok], dtype=np.int64)),
    }
    ds = xr.Dataset(per, coords={
        "ensemble": ("realisation", kind), "index": ("realisation", np.array([r[1] for r in ok])),
        "component": ["x", "y"], "station": stations, "load_step": np.arange(len(scene.load_factors)),
        "kind": list(KINDS), "quantile": list(QUANTILES), "outcome": list(OUTCOMES) + ["path_offset"],
        "source": ["total", "aleatoric", "epistemic"]})
    ds["position"] = (("particle", "component"), scene.x)
    ds["load_factors"] = ("load_step", scene.load_factors)
    _summaries(ds, kind, scene.threshold)
    if scene.observed_path is not None:
        ds["observed_path"] = (("observed_point", "component"), np.asarray(scene.observed_path, dtype=np.float64))
    failed = [r for r in results if "error" in r[2]]
    ds.attrs.update({
        "description": "posterior-predictive crack ensemble (Dodwell 2019 eq 4 with damage)",
        "threshold": scene.threshold, "path_threshold": scene.path_threshold, "seed": int(seed),
        "origin": [float(v) for v in scene.origin], "direction": [float(v) for v in scene.direction],
        "failure_length": np.nan if scene.failure_length is None else scene.failure_length,
        "realisations_posterior": int(np.sum(kind == "posterior")), "realisations_mean": int(np.sum(kind == "mean")),
        "failed": len(failed), "failed_realisations": "; ".join(f"{r[0]}-{r[1]}: {r[2]['error']}" for r in failed),
        **{f"scene_{k}": v for k, v in scene.attrs.items()}})
    return ds


def _summaries(ds, kind, threshold):
    groups = [kind == k for k in KINDS]
    phi = ds["phi"].values
    ds["probability"] = (("kind", "particle"), np.stack(
        [(phi[g] > threshold).mean(0) if g.any() else np.full(phi.shape[1], np.nan) for g in groups]))
    off = ds["offset"].values
    ds["path_quantiles"] = (("kind", "quantile", "station"), np.stack(
        [np.stack([quantiles(off[g, j]) for j in range(off.shape[1])], axis=1) for g in groups]))
    ds["path_coverage"] = (("kind", "station"), np.stack(
        [np.isfinite(off[g]).mean(0) if g.any() else np.full(off.shape[1], np.nan) for g in groups]))
    lengths = ds["crack_length_at_load"].values
    ds["crack_length_at_load_quantiles"] = (("kind", "quantile", "load_step"), np.stack(
        [np.stack([quantiles(lengths[g, j]) for j in range(lengths.shape[1])], axis=1) for g in groups]))
    for name in OUTCOMES:
        ds[f"{name}_quantiles"] = (("kind", "quantile"), np.stack([quantiles(ds[name].values[g]) for g in groups]))
    ds["failure_reached"] = ("kind", np.array(
        [np.isfinite(ds["failure_load_factor"].values[g]).mean() if g.any() else np.nan for g in groups]))
    spread = []
    for name in OUTCOMES + ("path_offset",):
        if name == "path_offset":  # mean over stations of the across-crack standard deviation
            total, alea = (_finite_mean([sd(off[g, j]) for j in range(off.shape[1])]) for g in groups)
        else:
            total, alea = (sd(ds[name].values[g]) for g in groups)
        epi = np.sqrt(max(0.0, total**2 - alea**2)) if np.isfinite(total) and np.isfinite(alea) else np.nan
        spread.append([total, alea, epi])
    ds["spread"] = (("outcome", "source"), np.array(spread))
