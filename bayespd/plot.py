"""Figures of a crack ensemble (the Dataset of ``bayespd.ensemble.predictive.ensemble``):
damage-probability map, path overlay with the credible band, failure-load histogram.
Each function draws on ``ax`` (a new figure if None) and returns the axes."""
from __future__ import annotations

import numpy as np

COLOURS = {"posterior": "tab:red", "mean": "tab:blue"}


def _axes(ax, size):
    if ax is None:
        import matplotlib.pyplot as plt
        ax = plt.figure(figsize=size, layout="constrained").add_subplot()
    return ax


def _observed(ax, ds):
    if "observed_path" in ds:
        p = ds["observed_path"].values
        ax.plot(p[:, 0], p[:, 1], "c--", lw=2, label="observed crack")


def damage_probability(ds, kind: str = "posterior", ax=None):
    """P(phi > threshold) per particle, the observed crack (if any) overlaid."""
    ax = _axes(ax, (6, 5))
    x = ds["position"].values
    im = ax.tripcolor(x[:, 0], x[:, 1], ds["probability"].sel(kind=kind).values,
                      shading="gouraud", cmap="magma_r", vmin=0, vmax=1)
    _observed(ax, ds)
    n = int(ds.attrs[f"realisations_{kind}"])
    ax.set(aspect="equal", xlabel="x", ylabel="y",
           title=f"P(phi > {ds.attrs['threshold']}) over {n} realisations ({kind})")
    ax.figure.colorbar(im, ax=ax)
    if "observed_path" in ds:
        ax.legend(loc="lower left")
    return ax


def _band(ds, kind):
    """The 5-95 % band of the path offset as points in the plane (lower, upper)."""
    o, d = np.asarray(ds.attrs["origin"]), np.asarray(ds.attrs["direction"])
    normal = np.array([-d[1], d[0]])
    s = ds["station"].values
    q = ds["path_quantiles"].sel(kind=kind)
    return [o + s[:, None] * d + q.sel(quantile=p).values[:, None] * normal for p in (0.05, 0.95)]


def path_overlay(ds, ax=None, max_paths: int = 100):
    """Crack paths of both ensembles and the posterior 5-95 % band across the crack line."""
    ax = _axes(ax, (7, 4))
    for kind in ("mean", "posterior"):
        paths = ds["path"].values[ds["ensemble"].values == kind][:max_paths]
        for i, p in enumerate(paths):
            ax.plot(p[:, 0], p[:, 1], "-", color=COLOURS[kind], alpha=0.3, lw=0.8,
                    label=f"{kind} ensemble" if i == 0 else None)
    lo, hi = _band(ds, "posterior")
    keep = np.isfinite(lo[:, 1]) & np.isfinite(hi[:, 1])
    ax.fill(np.r_[lo[keep, 0], hi[keep, 0][::-1]], np.r_[lo[keep, 1], hi[keep, 1][::-1]],
            color="k", alpha=0.15, label="posterior 5-95 % band")
    _observed(ax, ds)
    ax.set(xlabel="x", ylabel="y", title="crack paths (axes not to scale)")
    ax.legend(loc="best", fontsize=8)
    return ax


def failure_load_histogram(ds, ax=None, variable: str = "failure_load_factor"):
    """Histograms of ``variable`` for both ensembles with their 90 % credible intervals."""
    ax = _axes(ax, (6, 4))
    values = ds[variable].values
    finite = values[np.isfinite(values)]
    bins = np.histogram_bin_edges(finite, bins=20) if len(finite) else 10
    for kind in ("posterior", "mean"):
        v = values[(ds["ensemble"].values == kind) & np.isfinite(values)]
        if not len(v):
            continue
        lo, hi = ds[f"{variable}_quantiles"].sel(kind=kind, quantile=[0.05, 0.95]).values
        ax.hist(v, bins=bins, color=COLOURS[kind], alpha=0.5,
                label=f"{kind}: 90 % interval [{lo:.4g}, {hi:.4g}]")
        for q in (lo, hi):
            ax.axvline(q, color=COLOURS[kind], ls="--")
    ax.set(xlabel=variable.replace("_", " "), ylabel="realisations",
           title="failure load (posterior: total spread; mean: Brownian only)")
    ax.legend(fontsize=8)
    return ax


def ensemble_figures(ds, out) -> list:
    """Write the three figures as PNG beside ``out`` (atomically); returns their paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from pathlib import Path

    from bayespd.atomic import atomic_path

    paths = []
    for name, draw in (("damage_probability", damage_probability), ("crack_paths", path_overlay),
                       ("failure_load", failure_load_histogram)):
        ax = draw(ds)
        path = Path(out) / f"{name}.png"
        with atomic_path(path) as tmp:
            ax.figure.savefig(tmp, format="png", dpi=110)
        plt.close(ax.figure)
        paths.append(path)
    return paths
