"""``read_field``: a displacement field file as a :class:`bayespd.fields.Field` in one call.

Formats, by suffix:

* ``.txt``: DICe solution files (``bayespd.dic.read_dice``; a glob reads several frames, then
  ``frame=`` picks one); failed subsets (SIGMA < 0, a failed STATUS_FLAG, NaN) are masked.
* ``.csv``: VIC-3D / VIC-2D data exports (what Delorme 2018 reads, PeriPyDIC ``IO/dic.py``): a
  header row of column names, one row per subset. VIC names the metric (calibrated) positions
  and displacements X, Y, U, V and the image ones x, y, u, v; the metric ones are read when
  present, else the image ones, or name them with ``columns={"x": ..., "y": ..., "u": ...,
  "v": ..., "sigma": ...}``. ``sigma`` is VIC's confidence interval, -1 where the correlation
  failed; such rows, NaN entries and rows left empty are masked; rows without a position are
  dropped. VIC's metric positions are projected from 3D and not on an exact lattice: map them
  onto ``particles=`` (or read the image columns, which are).
* ``.npz``: arrays ``x`` (nx,), ``y`` (ny,), ``u``, ``v`` (and optional ``sigma``, ``valid``) of
  the grid, laid out by ``order`` (see ``bayespd.fields``).
* ``.nc``: NetCDF (xarray): variables ``u``, ``v`` (optional ``sigma``, ``valid``) with dims named
  ``x`` and ``y`` and those coordinates: the dims give the order.

``scale``, ``origin`` and ``flip_y`` map file units to model units (positions origin + scale *
(x, +-y), displacements scale * (u, +-v)): DICe and VIC image coordinates are pixels with y
pointing down. The other keywords go to ``bayespd.fields.from_point_field`` (particles, body,
thickness, edge).
"""
from __future__ import annotations

import glob
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from bayespd.dic import NAN_TEXT, frame_data, read_dice
from bayespd.fields import Field, from_grid_field, from_point_field
from bayespd.validate import finite, positive, readable_file, reading

VIC_COLUMNS = ({"x": "X", "y": "Y", "u": "U", "v": "V"}, {"x": "x", "y": "y", "u": "u", "v": "v"})


def _sign(flip_y: bool) -> np.ndarray:
    return np.array([1.0, -1.0 if flip_y else 1.0])


def _dice(path, frame, scale, origin, flip_y, mapping) -> Field:
    ds = read_dice(path)
    frames = ds["frame"].values.tolist()
    if frame is None:
        if len(frames) > 1:
            raise ValueError(f"{path} holds the frames {frames}: pass frame= to pick one")
        frame = frames[0]
    points, y, mask = frame_data(ds, frame, scale, origin, flip_y)
    sigma = scale * ds["sigma"].sel(frame=frame).values
    return from_point_field(points, y, sigma=sigma, valid=mask[:, 0], **mapping)


def _vic(path: Path, columns, scale, origin, flip_y, mapping) -> Field:
    with reading(path, "a VIC data export (CSV)", "export the data from VIC as CSV with a header row"):
        table = pd.read_csv(path, skipinitialspace=True, na_values=NAN_TEXT)
    table.columns = [str(c).strip().strip('"') for c in table.columns]
    if columns is None:
        columns = next((c for c in VIC_COLUMNS if set(c.values()) <= set(table.columns)), None)
        if columns is None:
            raise ValueError(f"{path} has the columns {list(table.columns)}, neither X, Y, U, V nor x, y, u, v: "
                             "name yours with columns={'x': ..., 'y': ..., 'u': ..., 'v': ...}")
        columns = {**columns, **({"sigma": "sigma"} if "sigma" in table.columns else {})}
    missing = [columns.get(k, k) for k in ("x", "y", "u", "v") if columns.get(k, k) not in table.columns]
    missing += [columns["sigma"]] if "sigma" in columns and columns["sigma"] not in table.columns else []
    if missing:
        raise ValueError(f"{path} lacks the column(s) {missing} (it has {list(table.columns)}): fix columns=")
    text = [c for c in columns.values() if not pd.api.types.is_numeric_dtype(table[c])]
    if text:
        raise ValueError(f"{path} has non-numeric entries in the column(s) {text}: fix or drop those rows")
    table = table[np.isfinite(table[[columns["x"], columns["y"]]].to_numpy(float)).all(axis=1)]
    if table.empty:
        raise ValueError(f"{path} lists no point with a position")
    sign = _sign(flip_y)
    points = np.asarray(origin, float) + scale * sign * table[[columns["x"], columns["y"]]].to_numpy(float)
    u = scale * sign * table[[columns["u"], columns["v"]]].to_numpy(float)
    sigma = scale * table[columns["sigma"]].to_numpy(float) if "sigma" in columns else None
    return from_point_field(points, u, sigma=sigma, **mapping)


def _grid(arrays: dict, path: Path, order, scale, origin, flip_y, mapping) -> Field:
    missing = [k for k in ("x", "y", "u", "v") if k not in arrays]
    if missing:
        raise ValueError(f"{path} lacks {missing}: a grid file needs x (nx,), y (ny,), u and v (and may hold "
                         "sigma and valid)")
    sign = _sign(flip_y)
    x = origin[0] + scale * np.asarray(arrays["x"], float)
    y = origin[1] + scale * sign[1] * np.asarray(arrays["y"], float)
    sigma = arrays.get("sigma")
    return from_grid_field(x, y, scale * arrays["u"], scale * sign[1] * arrays["v"], order=order,
                           sigma=None if sigma is None else scale * sigma, valid=arrays.get("valid"), **mapping)


def _netcdf(path: Path):
    with reading(path, "a NetCDF grid (xarray)", "write it with xarray's to_netcdf"):
        ds = xr.load_dataset(path)
    arrays = {k: ds[k] for k in ("u", "v", "sigma", "valid") if k in ds}
    if "u" in ds and not {"x", "y"} <= set(ds["u"].dims):
        raise ValueError(f"{path}: u has dims {ds['u'].dims}; name the grid's dims 'x' and 'y' (they give the order)")
    return {**arrays, **{k: ds[k].values for k in ("x", "y") if k in ds.coords}}


def read_field(path, *, frame: int | None = None, order: str | None = None, columns: dict | None = None,
               scale: float = 1.0, origin=(0.0, 0.0), flip_y: bool = False, **mapping) -> Field:
    """The field in ``path`` (DICe ``.txt`` or a glob of them, VIC ``.csv``, ``.npz``, NetCDF
    ``.nc``; see the module docstring) on particles, as a :class:`bayespd.fields.Field`."""
    positive("scale", scale, "pass the model units per file unit")
    origin = np.asarray(finite("origin", origin, "pass the model position of the file's (0, 0)"), float)
    suffix = Path(str(path)).suffix.lower()
    if suffix == ".txt":
        return _dice(path, frame, scale, origin, flip_y, mapping)
    if glob.has_magic(str(path)):
        raise ValueError(f"a glob ({path}) reads DICe .txt frames only: pass one file")
    path = readable_file(path, "field file")
    if frame is not None:
        raise ValueError(f"frame= picks a DICe frame; {path.name} holds one field: drop frame")
    if columns is not None and suffix != ".csv":
        raise ValueError(f"columns= names the columns of a VIC .csv; {path.name} is not one: drop columns")
    if suffix == ".csv":
        return _vic(path, columns, scale, origin, flip_y, mapping)
    if suffix == ".npz":
        with reading(path, "a NumPy .npz grid", "write it with numpy.savez(path, x=..., y=..., u=..., v=...)"):
            with np.load(path) as archive:
                arrays = dict(archive)
        return _grid(arrays, path, order, scale, origin, flip_y, mapping)
    if suffix == ".nc":
        return _grid(_netcdf(path), path, order, scale, origin, flip_y, mapping)
    raise ValueError(f"unknown field file type {path.suffix!r} ({path.name}): read_field reads DICe .txt, "
                     "VIC .csv, .npz and NetCDF .nc")
