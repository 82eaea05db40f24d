"""Inference results as an ``xarray.DataTree`` with ArviZ group names, NetCDF I/O, summary.

Groups: ``posterior``, ``sample_stats``, ``log_likelihood``, ``posterior_predictive``
(variables with leading dims ``(chain, draw)``) and ``observed_data``. Run settings live in
the root attributes (numbers and strings; dict-like settings as JSON strings), so they
survive a NetCDF round trip.
"""

import os
import warnings

import arviz as az
import numpy as np
import xarray as xr

from bayespd.atomic import atomic_path

SAMPLE_DIMS = ("chain", "draw")


def build_tree(groups, attrs=None, dims=None, coords=None) -> xr.DataTree:
    """DataTree from ``{group: {variable: array}}`` (or ``{group: Dataset}``, kept as is).

    Arrays start with ``(chain, draw)`` except in ``observed_data``. The remaining axes of
    variable ``v`` are named ``dims[v]`` (padded or cut to length) or ``v_dim_0``, ...;
    ``coords`` supplies coordinate values for those dims.
    """
    nodes = {"/": xr.Dataset(attrs=attrs or {})}
    for group, arrays in groups.items():
        sample_dims = () if group == "observed_data" else SAMPLE_DIMS
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
    """Read a tree written by :func:`save`, fully into memory (the file is closed)."""
    with xr.open_datatree(os.fspath(path), engine="h5netcdf") as tree:
        return tree.load()


def summary(tree: xr.DataTree, var_names=None):
    """``az.summary`` of the posterior (mean, sd, 90 % HDI, MCSE, bulk/tail ESS, r_hat).

    Warns (``UserWarning``) when some r_hat exceeds 1.05 or the sampler diverged.
    """
    df = az.summary(to_inference_data(tree), var_names=var_names, hdi_prob=0.9)
    if (df["r_hat"] > 1.05).any():
        bad = ", ".join(df.index[df["r_hat"] > 1.05])
        warnings.warn(f"r_hat > 1.05 for {bad}: chains have not mixed", UserWarning)
    if "sample_stats" in tree.children and "diverging" in tree["sample_stats"]:
        n = int(tree["sample_stats"]["diverging"].sum())
        if n:
            warnings.warn(f"{n} divergent transitions: the posterior may be biased", UserWarning)
    return df
