"""Inference results as an ``xarray.DataTree`` with ArviZ group names, NetCDF I/O, summary.

Groups: ``posterior``, ``sample_stats``, ``log_likelihood``, ``posterior_predictive``
(variables with leading dims ``(chain, draw)``), ``observed_data`` and ``constant_data``
(the other model inputs, e.g. the mask and observation points). Run settings live in
the root attributes (numbers and strings; dict-like settings as JSON strings), so they
survive a NetCDF round trip.
"""

import json
import os
import warnings

import arviz as az
import numpy as np
import xarray as xr

from bayespd.atomic import atomic_path
from bayespd.materials import young_from_moduli
from bayespd.validate import in_range, readable_file, reading

SAMPLE_DIMS = ("chain", "draw")
DATA_GROUPS = ("observed_data", "constant_data")
# Vehtari, Gelman, Simpson, Carpenter & Buerkner (2021), the thresholds ArviZ and Stan use
R_HAT_MAX, ESS_PER_CHAIN_MIN, BFMI_MIN = 1.01, 100, 0.3


def build_tree(groups, attrs=None, dims=None, coords=None) -> xr.DataTree:
    """DataTree from ``{group: {variable: array}}`` (or ``{group: Dataset}``, kept as is).

    Arrays start with ``(chain, draw)`` except in ``observed_data`` and ``constant_data``. The remaining axes of
    variable ``v`` are named ``dims[v]`` (padded or cut to length) or ``v_dim_0``, ...;
    ``coords`` supplies coordinate values for those dims.
    """
    nodes = {"/": xr.Dataset(attrs=attrs or {})}
    for group, arrays in groups.items():
        sample_dims = () if group in DATA_GROUPS else SAMPLE_DIMS
        if not isinstance(arrays, xr.Dataset):
            arrays = _dataset(arrays, sample_dims, dims or {}, coords or {})
        nodes[group] = arrays
    return xr.DataTree.from_dict(nodes)


def _dataset(arrays, sample_dims, dims, coords):
    data_vars = {}
    for name, value in arrays.items():
        value = np.asarray(value)
        n = value.ndim - len(sample_dims)
        given = list(dims.get(name, []))[:n]
        names = given + [f"{name}_dim_{i}" for i in range(len(given), n)]
        data_vars[name] = ((*sample_dims, *names), value)
    ds = xr.Dataset(data_vars)
    ds = ds.assign_coords({k: v for k, v in coords.items() if k in ds.dims})
    return ds.assign_coords({d: np.arange(ds.sizes[d]) for d in sample_dims})


def to_inference_data(tree: xr.DataTree) -> az.InferenceData:
    """ArviZ InferenceData with the same groups; root attributes become ``idata.attrs``."""
    groups = {name: node.to_dataset() for name, node in tree.children.items()}
    return az.InferenceData(attrs=dict(tree.attrs), **groups)


def save(tree: xr.DataTree, path) -> None:
    """Write ``tree`` to NetCDF (h5netcdf) atomically: temp file in the same folder, then rename."""
    with atomic_path(path) as tmp:
        tree.to_netcdf(tmp, engine="h5netcdf")


def load(path) -> xr.DataTree:
    """Read a tree written by :func:`save`, fully into memory (the file is closed); a missing
    file raises ``FileNotFoundError``, a truncated or foreign one ``ValueError`` naming it."""
    path = readable_file(path, "result file")
    with reading(path, "a NetCDF result tree", "it is truncated or not written by bayespd.infer.save: "
                 "fit again, or pass the right file"):
        with xr.open_datatree(os.fspath(path), engine="h5netcdf") as tree:
            return tree.load()


def summary(tree: xr.DataTree, var_names=None):
    """``az.summary`` of the posterior (mean, sd, 90 % HDI, MCSE of mean and sd, bulk/tail
    ESS, r_hat) with a ``UserWarning`` for each failed diagnostic of an MCMC fit, by the
    thresholds of Vehtari et al. (2021) that ArviZ and Stan use: r_hat > 1.01, bulk or tail
    ESS < 100 per chain, any divergent transition, E-BFMI < 0.3 in some chain, and draws that
    hit the maximum tree depth. SVI and Laplace draws are independent: only divergences (none)
    would apply, so they get no warnings. A fit that mixed several modes
    (``fit(..., modes="weighted")``) carries their table (:func:`modes`) in
    ``df.attrs["modes"]``.
    """
    df = az.summary(to_inference_data(tree), var_names=var_names, hdi_prob=0.9)
    if (table := modes(tree, mixed=True)) is not None:
        df.attrs["modes"] = table
    if tree.attrs.get("method") in ("nuts", "hmc"):
        for message in _diagnostic_failures(tree, df):
            warnings.warn(message, UserWarning, stacklevel=2)
    return df


def modes(tree: xr.DataTree, mixed: bool = False):
    """The modes the MAP search found, one row each (``pandas.DataFrame``): potential, the
    scalar parameters' values and, for ``fit(..., modes="weighted")``, each mode's Laplace log
    mass, the log mass it was weighted by (``mixture``), its weight and number of draws; None
    for a fit that records no modes, and with ``mixed`` unless its draws mix several modes."""
    import pandas as pd

    text = tree.attrs.get("mode_weights", tree.attrs.get("map_modes"))
    if text is None:
        return None
    rows = []
    for mode in json.loads(text):
        values = {k: v for k, v in mode.pop("values").items() if np.ndim(v) == 0}
        rows.append({**mode, **values})
    table = pd.DataFrame(rows).rename_axis("mode")
    return None if mixed and ("weight" not in table or len(table) < 2) else table


def young_intervals(tree: xr.DataTree, level: float = 0.9) -> dict:
    """Young's modulus E and Poisson's ratio nu over the posterior draws of K, G (``young_from_moduli``:
    E = 9 K G / (3 K + G), nu = (3 K - 2 G) / (2 (3 K + G))): per name its ``mean``, ``sd`` and central
    ``level`` interval (``interval_90`` for 0.9: the 5 % and 95 % quantiles)."""
    in_range("level", level, 0.0, 1.0, "give the interval's probability, e.g. 0.9", closed=(False, False))
    post = tree["posterior"]
    missing = {"K", "G"} - set(post.data_vars)
    if missing:
        raise ValueError(f"the posterior has no {sorted(missing)}: E and nu need draws of the moduli K and G")
    E, nu = young_from_moduli(post["K"].values.reshape(-1), post["G"].values.reshape(-1))
    q = [(1 - level) / 2, (1 + level) / 2]
    key = f"interval_{100 * level:g}"
    return {k: {"mean": float(np.mean(v)), "sd": float(np.std(v)), key: np.quantile(v, q).tolist()}
            for k, v in (("E", np.asarray(E)), ("nu", np.asarray(nu)))}


def _diagnostic_failures(tree, df):
    chains = tree["posterior"].sizes["chain"]
    if (df["r_hat"] > R_HAT_MAX).any():
        bad = ", ".join(df.index[df["r_hat"] > R_HAT_MAX])
        yield f"r_hat > {R_HAT_MAX} for {bad}: the chains have not mixed; run longer warmup or more draws"
    ess_min = ESS_PER_CHAIN_MIN * chains
    for kind in ("bulk", "tail"):
        low = df[f"ess_{kind}"] < ess_min
        if low.any():
            yield (f"{kind} ESS < {ess_min} (100 per chain) for {', '.join(df.index[low])}: "
                   "too few effective draws for reliable intervals; draw more")
    st = tree["sample_stats"] if "sample_stats" in tree.children else None
    if st is None:
        return
    if "diverging" in st and (n := int(st["diverging"].sum())):
        yield (f"{n} divergent transitions: the posterior may be biased; raise target_accept, "
               "use a dense mass matrix or reparametrise")
    if "energy" in st:
        bfmi = az.bfmi(st["energy"].values)
        if (bfmi < BFMI_MIN).any():
            yield (f"E-BFMI {np.round(bfmi, 2).tolist()} < {BFMI_MIN}: the momentum resampling "
                   "explores the energy poorly; reparametrise or use a dense mass matrix")
    depth = json.loads(tree.attrs.get("settings", "{}")).get("max_tree_depth")
    if "tree_depth" in st and depth is not None and (st["tree_depth"] >= depth).any():
        yield (f"{int((st['tree_depth'] >= depth).sum())} draws hit max_tree_depth {depth}: "
               "trajectories were cut short; use a dense mass matrix or raise max_tree_depth")
