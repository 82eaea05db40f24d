"""ParaView output: particles and their fields as VTK XML UnstructuredGrid files (``.vtu``, one
vertex cell per particle) and time series as ``.pvd`` collections. Plain XML written here
(ascii, shortest round-trip digits), so no VTK library is needed; every write is atomic.
"""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import torch

from bayespd.atomic import atomic_path
from bayespd.discretize import Particles

VTK_VERTEX = 1


def _write_atomic(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def _array(parent: ET.Element, values: np.ndarray, name: str | None = None) -> None:
    """A DataArray of Float64 or Int64 values, one row per point, in ascii."""
    kind = "Float64" if values.dtype.kind == "f" else "Int64"
    attrs = {"type": kind, "format": "ascii"}
    if name is not None:
        attrs["Name"] = name
    if values.ndim == 2:
        attrs["NumberOfComponents"] = str(values.shape[1])
    node = ET.SubElement(parent, "DataArray", attrs)
    node.text = " ".join(map(repr, values.ravel().tolist()))


def _field(name: str, value, n: int) -> np.ndarray:
    """A per-particle field as numpy: (N,) or (N, k), 2-vectors padded to 3 components."""
    a = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
    if a.dtype.kind not in "fiub" or a.ndim not in (1, 2) or a.shape[0] != n:
        raise ValueError(f"field {name!r} must be numbers of shape ({n},) or ({n}, k), got {a.dtype} {a.shape}")
    a = a.astype(float if a.dtype.kind == "f" else np.int64)
    return np.pad(a, ((0, 0), (0, 1))) if a.ndim == 2 and a.shape[1] == 2 else a


def write_vtu(path, x, **fields) -> Path:
    """Write particles ``x`` (a :class:`Particles`, whose volumes are written too, or an (N, dim)
    array) with per-particle ``fields`` (e.g. ``displacement=u, damage=d``; each (N,) or (N, k))
    to ``path`` (.vtu). 2D positions get z = 0."""
    if isinstance(x, Particles):
        fields = {"volume": x.volume, **fields}
        x = x.x
    n, path = len(x), Path(path)
    points = _field("positions", x, n).astype(float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"positions must be (N, 2) or (N, 3), got {np.shape(x)}")
    root = ET.Element("VTKFile", type="UnstructuredGrid", version="1.0", byte_order="LittleEndian")
    piece = ET.SubElement(ET.SubElement(root, "UnstructuredGrid"), "Piece",
                          NumberOfPoints=str(n), NumberOfCells=str(n))
    data = ET.SubElement(piece, "PointData")
    for name, value in fields.items():
        _array(data, _field(name, value, n), name)
    _array(ET.SubElement(piece, "Points"), points)
    cells = ET.SubElement(piece, "Cells")
    _array(cells, np.arange(n), "connectivity")
    _array(cells, np.arange(1, n + 1), "offsets")
    _array(cells, np.full(n, VTK_VERTEX), "types")
    _write_atomic(path, ET.tostring(root, xml_declaration=True, encoding="utf-8"))
    return path


def write_pvd(path, entries) -> Path:
    """A ParaView collection ``path`` (.pvd) of ``(time, file)`` entries; files are stored
    relative to the collection's folder."""
    path = Path(path)
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    collection = ET.SubElement(root, "Collection")
    for time, file in entries:
        ET.SubElement(collection, "DataSet", timestep=repr(float(time)), group="", part="0",
                      file=os.path.relpath(Path(file).resolve(), path.parent.resolve()))
    _write_atomic(path, ET.tostring(root, xml_declaration=True, encoding="utf-8"))
    return path


class Series:
    """A time series for ParaView: ``write(time, x, **fields)`` writes ``<stem>_<k>.vtu``
    beside ``path`` (.pvd) and rewrites the collection, so it is complete after every frame."""

    def __init__(self, path):
        self.path = Path(path)
        self.entries: list[tuple[float, Path]] = []

    def write(self, time: float, x, **fields) -> Path:
        if self.entries and not time > self.entries[-1][0]:
            raise ValueError(f"times must increase: {time} after {self.entries[-1][0]}")
        file = write_vtu(self.path.with_name(f"{self.path.stem}_{len(self.entries):04d}.vtu"), x, **fields)
        self.entries.append((float(time), file))
        write_pvd(self.path, self.entries)
        return file
