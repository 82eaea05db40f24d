"""MD records as NetCDF: the schema, atomic writes, a settings-hash cache, a validating reader.

A record is an ``xarray.Dataset`` with dims ``frame``, ``atom``, ``dim`` (x, y) and

* ``X`` (atom, dim): reference positions, angstrom; ``M`` (atom): masses, g/mol;
* ``U`` (frame, atom, dim): displacements, angstrom; ``B`` (frame, atom, dim): external force
  per atom, eV/angstrom (LAMMPS ``metal`` units);
* ``time`` (frame): ps (0 for the static sets; their ``case`` names each load);
* ``prescribed`` (atom): atoms whose motion is prescribed (the pulled edges), bool;
* attributes: ``kind``, ``settings`` (JSON), ``settings_hash``, ``periodic``, ``box`` (A, for a
  periodic record), ``potential``, ``max_bond_strain``, ``wall_time_s``.

The reader refuses a file with a missing array, a wrong unit, a NaN, or atoms that left the sheet
(further than ``margin`` outside the reference positions' bounding box), naming the fix.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Callable

import numpy as np
import xarray as xr

from bayespd.atomic import atomic_path
from bayespd.validate import readable_file, reading

FORMAT_VERSION = 1
UNITS = {"X": "angstrom", "U": "angstrom", "B": "eV/angstrom", "M": "g/mol", "time": "ps"}
DIMS = {"X": ("atom", "dim"), "U": ("frame", "atom", "dim"), "B": ("frame", "atom", "dim"), "M": ("atom",),
        "time": ("frame",)}


def record(x, u, b, mass, time, *, kind: str, settings: dict, prescribed=None, case=None, periodic=False,
           box=None, **attrs) -> xr.Dataset:
    """A record from numpy arrays (x (n, 2), u and b (frames, n, 2), mass (n,), time (frames,))."""
    u = np.asarray(u, float)
    data = {"X": (DIMS["X"], np.asarray(x, float)), "U": (DIMS["U"], u), "B": (DIMS["B"], np.asarray(b, float)),
            "M": (DIMS["M"], np.asarray(mass, float)), "time": (DIMS["time"], np.asarray(time, float)),
            "prescribed": (("atom",), np.zeros(u.shape[1], bool) if prescribed is None else np.asarray(prescribed))}
    if case is not None:
        data["case"] = (("frame",), np.asarray(case, dtype=str))
    ds = xr.Dataset(data, coords={"dim": ["x", "y"]})
    for name, unit in UNITS.items():
        ds[name].attrs["units"] = unit
    ds.attrs.update(kind=kind, settings=json.dumps(settings, sort_keys=True), settings_hash=settings_hash(kind, settings),
                    periodic=int(periodic), **attrs)
    if box is not None:
        ds.attrs["box"] = np.asarray(box, float)
    return ds


def settings_hash(kind: str, settings: dict) -> str:
    """SHA-256 of the kind, the settings (JSON, sorted keys) and the format version."""
    text = json.dumps({"kind": kind, "settings": settings, "format": FORMAT_VERSION}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def write_md(ds: xr.Dataset, path) -> Path:
    """Write ``ds`` to ``path`` (NetCDF4 via h5netcdf) atomically: readers never see half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        ds.to_netcdf(tmp, engine="h5netcdf")
    return path


def check_md(ds: xr.Dataset, source: str = "the record", margin: float = 10.0) -> xr.Dataset:
    """``ds`` if it is a complete, finite record in the units above whose atoms stay on the sheet."""
    missing = [n for n in DIMS if n not in ds.variables]
    if missing:
        raise ValueError(f"{source} lacks the array(s) {missing}: remake it with bayespd.learn.md "
                         f"(a record holds {sorted(DIMS)})")
    for name, unit in UNITS.items():
        got = ds[name].attrs.get("units")
        if got != unit:
            raise ValueError(f"{source}: {name} is in {got!r}, not {unit!r}: convert it to {unit} "
                             "(LAMMPS metal units) and set its 'units' attribute")
        if tuple(ds[name].dims) != DIMS[name]:
            raise ValueError(f"{source}: {name} has dims {ds[name].dims}, expected {DIMS[name]}")
        if not np.isfinite(ds[name].values).all():
            raise ValueError(f"{source}: {name} contains NaN or inf: the run diverged; lower the load or the time step")
    left = _left_the_sheet(ds, margin)
    if left is not None:
        frame, n = left
        raise ValueError(f"{source}: {n} atom(s) left the sheet (more than {margin:g} A outside the reference "
                         f"bounding box, or more than half a periodic box from home) at frame {frame}: keep the "
                         f"frames before it (ds.isel(frame=slice(0, {frame}))), lower the load, or raise margin=")
    return ds


def _left_the_sheet(ds: xr.Dataset, margin: float):
    """(first frame, atom count) of atoms off the sheet, or None."""
    x, u = ds["X"].values, ds["U"].values
    if ds.attrs.get("periodic", 0):
        off = (np.abs(u) > np.asarray(ds.attrs["box"], float) / 2.0).any(axis=2)
    else:
        lo, hi = x.min(axis=0) - margin, x.max(axis=0) + margin
        y = x[None] + u
        off = ((y < lo) | (y > hi)).any(axis=2)
    frames = np.flatnonzero(off.any(axis=1))
    return None if frames.size == 0 else (int(frames[0]), int(off[frames[0]].sum()))


def read_md(path, margin: float = 10.0) -> xr.Dataset:
    """The record in ``path``, loaded into memory and checked (``check_md``)."""
    path = readable_file(path, "an MD record (NetCDF)")
    with reading(path, "an MD record (NetCDF)", "remake it with bayespd.learn.md"):
        with xr.open_dataset(path, engine="h5netcdf") as ds:
            ds = ds.load()
    return check_md(ds, str(path), margin)


def cached(kind: str, settings: dict, directory, make: Callable[[], xr.Dataset], margin: float = 10.0) -> xr.Dataset:
    """The record of ``kind`` with ``settings``: read from ``directory`` when a file with the same
    settings hash is there, else made by ``make()``, checked and written atomically."""
    path = Path(directory) / f"{kind}-{settings_hash(kind, settings)[:16]}.nc"
    if path.exists():
        return read_md(path, margin)
    ds = check_md(make(), f"the new {kind} record", margin)
    write_md(ds, path)
    return ds
