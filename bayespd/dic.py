"""Read DICe (Digital Image Correlation Engine, Sandia) solution files into an xarray Dataset.

DICe writes one comma-separated file per frame, ``<prefix>_<frame>.txt`` (``.<procs>.txt``
after parallel runs), with header lines starting ``***``, then a row of column names and one
row per subset. Its manual (github.com/dicengine/dice, doc/doxygen/DICe_MainPage.md, "Fields")
says SIGMA is the predicted std. dev. of the displacement and SIGMA = -1 a failed correlation;
STATUS_FLAG holds the ``DICe::Status_Flag`` enum (src/base/DICe.h): 0-4, 6 and 18 report a
successful correlation or initialisation; the others a failed or skipped step (5, 7-14, 16,
17, 19-25, 27-31), values averaged from neighbours (15) or a reset reference subset (26).
"""
from __future__ import annotations

import glob
import io
import re
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from bayespd.validate import finite, positive, reading

REQUIRED = ("COORDINATE_X", "COORDINATE_Y", "DISPLACEMENT_X", "DISPLACEMENT_Y", "SIGMA", "STATUS_FLAG")
SUCCESS = (0, 1, 2, 3, 4, 6, 18)  # DICe::Status_Flag values of a measured, successful subset
NAN_TEXT = ["NAN", "-NAN", "NAN(IND)", "-NAN(IND)", "nan(ind)", "-nan(ind)"]  # C's %E / %e NaN (glibc, MSVC)


def _frame_number(path: Path) -> int:
    found = re.search(r"(\d+)(\.\d+)?$", path.stem)
    if found is None:
        raise ValueError(f"no frame number at the end of the file name {path.name}: "
                         "name the files like DICe_solution_<frame>.txt")
    return int(found.group(1))


def _files(paths) -> list[Path]:
    if isinstance(paths, (str, Path)):
        paths = sorted(glob.glob(str(paths))) if glob.has_magic(str(paths)) else [paths]
    files = [Path(p) for p in paths]
    if not files:
        raise FileNotFoundError("no DICe files match: check the glob pattern or the folder")
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise FileNotFoundError(f"no such DICe file(s): {missing}")
    files.sort(key=_frame_number)
    numbers = [_frame_number(f) for f in files]
    if len(set(numbers)) < len(numbers):
        raise ValueError(f"two files share a frame number in {[f.name for f in files]}: read one DICe run at a time")
    return files


def _fields(line: str) -> int:
    """Comma-separated fields of a line, a trailing delimiter not counted."""
    parts = line.rstrip("\r\n").split(",")
    return len(parts) - (len(parts) > 1 and not parts[-1].strip())


def _table(path: Path) -> pd.DataFrame:
    """One solution file: the rows after the ``***`` header, sorted by SUBSET_ID when present."""
    with reading(path, "a DICe solution file (text)", "pass the comma-separated .txt files DICe writes"):
        lines = path.read_text().splitlines(keepends=True)
    if any("\x00" in line for line in lines):
        raise ValueError(f"{path} is a binary file, not a DICe solution file: pass the .txt files DICe writes")
    start = next((i for i, line in enumerate(lines) if line.strip() and not line.startswith(("***", "#"))), None)
    if start is None or "," not in lines[start]:
        raise ValueError(f"{path} has no comma-separated column header: read_dice reads DICe solution "
                         "files written with the default output_delimiter ','")
    width = _fields(lines[start])
    for number, line in enumerate(lines[start + 1:], start + 2):
        if line.strip() and _fields(line) != width:
            raise ValueError(f"{path}, line {number}: {_fields(line)} fields where the header has {width} "
                             "(a truncated or damaged file?): re-export it from DICe or delete that row")
    with reading(path, "a DICe solution file (text)"):
        table = pd.read_csv(io.StringIO("".join(lines[start:])), skipinitialspace=True, na_values=NAN_TEXT)
    if table.empty:
        raise ValueError(f"{path} lists no subsets")
    table.columns = table.columns.str.strip().str.upper()
    missing = [c for c in REQUIRED if c not in table.columns]
    if missing:
        raise ValueError(f"{path} lacks the column(s) {missing}: add them to the DICe output_spec "
                         f"(read_dice needs {list(REQUIRED)})")
    text = [c for c in REQUIRED if not pd.api.types.is_numeric_dtype(table[c])]
    if text:
        raise ValueError(f"{path} has non-numeric entries in the column(s) {text}: fix or drop those rows")
    if "SUBSET_ID" in table.columns:
        table = table.sort_values("SUBSET_ID", kind="stable")
    return table.reset_index(drop=True)


def read_dice(paths) -> xr.Dataset:
    """DICe solution files (a list, or a glob such as ``"results/DICe_solution_*.txt"``), one
    per frame, sorted by the frame number in the name, as a Dataset with dims
    ``(frame, point, component)``: ``displacement``, ``sigma``, ``status`` and ``mask`` (valid =
    finite displacement, SIGMA >= 0 and a successful STATUS_FLAG), with the subset positions
    ``x``, ``y`` (image coordinates: pixels, y down) as coordinates. Every frame must list the
    same subsets at the same positions.
    """
    files = _files(paths)
    tables = [_table(f) for f in files]
    first = tables[0]
    keys = [c for c in ("SUBSET_ID", "COORDINATE_X", "COORDINATE_Y") if c in first]
    for f, t in zip(files[1:], tables[1:]):
        if len(t) != len(first) or not all(c in t and np.array_equal(t[c], first[c]) for c in keys):
            raise ValueError(f"{f.name} does not list the same subsets at the same positions as {files[0].name}: "
                             "read frames of one DICe run (same subsets) together")
    u = np.stack([t[["DISPLACEMENT_X", "DISPLACEMENT_Y"]].to_numpy(float) for t in tables])
    sigma = np.stack([t["SIGMA"].to_numpy(float) for t in tables])
    flag = np.stack([t["STATUS_FLAG"].to_numpy(float) for t in tables])
    status = np.where(np.isfinite(flag), flag, -1).astype(int)
    mask = np.isfinite(u).all(axis=-1) & (sigma >= 0) & np.isin(status, SUCCESS)
    point = first["SUBSET_ID"].to_numpy() if "SUBSET_ID" in first else np.arange(len(first))
    return xr.Dataset(
        {"displacement": (("frame", "point", "component"), u), "sigma": (("frame", "point"), sigma),
         "status": (("frame", "point"), status), "mask": (("frame", "point"), mask)},
        coords={"frame": [_frame_number(f) for f in files], "point": point, "component": ["x", "y"],
                "x": ("point", first["COORDINATE_X"].to_numpy(float)),
                "y": ("point", first["COORDINATE_Y"].to_numpy(float))},
        attrs={"source": "DICe", "files": ", ".join(f.name for f in files)})


def frame_data(ds: xr.Dataset, frame: int, scale: float = 1.0, origin=(0.0, 0.0), flip_y: bool = False):
    """``(points, y, mask)`` of one frame for a model: points (n, 2) = origin + scale * (x, y),
    y (n, 2) = scale * displacement, mask (n, 2) boolean (the shape of y). ``scale`` converts
    pixels to model units; ``flip_y`` turns DICe's downward image y axis upward (negating y
    and the y displacement). Pass y and mask (with any other mask, ``&``) to
    :func:`bayespd.observe.model_data`.
    """
    positive("scale", scale, "pass the model units per pixel")
    finite("origin", origin, "pass the model position of pixel (0, 0)")
    if frame not in ds["frame"].values:
        raise ValueError(f"no frame {frame}: the data set has frames {ds['frame'].values.tolist()}")
    one = ds.sel(frame=frame)
    sign = np.array([1.0, -1.0 if flip_y else 1.0])
    points = np.asarray(origin, float) + scale * sign * np.stack([ds["x"].values, ds["y"].values], axis=1)
    y = scale * sign * one["displacement"].values
    return points, y, np.repeat(one["mask"].values[:, None], 2, axis=1)
