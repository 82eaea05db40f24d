"""Particles: reference positions ``x``, volumes, grid spacing ``h`` and thickness (2D)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from bayespd.validate import positive


@dataclass(frozen=True)
class Particles:
    """A set of particles (EMU nodal discretisation, Delorme 2018 §2.2.4).

    ``x`` is (N, dim) reference positions, ``volume`` (N,) the cell volumes (h*h*t in 2D),
    ``h`` the nominal spacing used by the partial-volume rule, ``thickness`` the out-of-plane
    thickness of a 2D body (1 for 3D).
    """

    x: np.ndarray
    volume: np.ndarray
    h: float
    thickness: float = 1.0

    def __post_init__(self):
        if self.x.ndim != 2 or self.x.shape[1] not in (2, 3):
            raise ValueError(f"x must be (N, 2) or (N, 3), got {self.x.shape}")
        if self.volume.shape != (len(self.x),):
            raise ValueError("volume must have one entry per particle")
        if not (np.all(np.isfinite(self.x)) and np.all(np.isfinite(self.volume))):
            raise ValueError("particle positions or volumes contain NaN or inf: clean the input")
        if np.any(self.volume <= 0):
            k = int(np.flatnonzero(self.volume <= 0)[0])
            raise ValueError(f"{int(np.sum(self.volume <= 0))} particle(s) have zero or negative "
                             f"volume (e.g. particle {k} at {self.x[k].tolist()}): fix or drop "
                             "degenerate cells")
        positive("the particle spacing h", self.h)
        positive("the thickness", self.thickness)
        if np.abs(self.x).max() > COORDINATE_LIMIT or not COORDINATE_LIMIT ** -1 <= self.h <= COORDINATE_LIMIT:
            raise ValueError(f"particle positions (largest |x| {np.abs(self.x).max():g}) or the spacing "
                             f"h={self.h:g} lie beyond 1e{np.log10(COORDINATE_LIMIT):.0f} (or h below its "
                             "inverse): squared distances overflow float64; rescale the units")
        _refuse_duplicates(self.x, self.h)

    @property
    def n(self) -> int:
        return len(self.x)

    @property
    def dim(self) -> int:
        return self.x.shape[1]

    def lower(self) -> np.ndarray:
        return self.x.min(axis=0) - self.h / 2

    def upper(self) -> np.ndarray:
        return self.x.max(axis=0) + self.h / 2

    def where(self, keep: np.ndarray) -> "Particles":
        """The particles for which the boolean mask ``keep`` is true (e.g. to cut a hole)."""
        keep = np.asarray(keep, dtype=bool)
        if not keep.any():
            raise ValueError("the mask removes every particle")
        return Particles(self.x[keep], self.volume[keep], self.h, self.thickness)

    def layer(self, side: str, depth: float) -> np.ndarray:
        """Mask of the particles within ``depth`` of one side of the bounding box.

        ``side`` is one of left, right, bottom, top (and front, back in 3D).
        """
        sides = {"left": (0, 0), "right": (0, 1), "bottom": (1, 0), "top": (1, 1),
                 "front": (2, 0), "back": (2, 1)}
        if side not in sides or sides[side][0] >= self.dim:
            raise ValueError(f"side must be one of {list(sides)[: 2 * self.dim]}, got {side!r}")
        axis, upper = sides[side]
        if upper:
            return self.x[:, axis] > self.upper()[axis] - depth
        return self.x[:, axis] < self.lower()[axis] + depth

    def interior(self, depth: float) -> np.ndarray:
        """Mask of the particles farther than ``depth`` from every side of the bounding box
        (e.g. those whose families are complete: depth = delta + h/2)."""
        return np.all((self.x > self.lower() + depth) & (self.x < self.upper() - depth), axis=1)

    def box(self, lo, hi) -> np.ndarray:
        """Mask of the particles inside the axis-aligned box [lo, hi]."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        return np.all((self.x >= lo) & (self.x <= hi), axis=1)

    def region(self, predicate) -> np.ndarray:
        """Mask from a vectorised predicate ``predicate(x) -> bool array``."""
        mask = np.asarray(predicate(self.x), dtype=bool)
        if mask.shape != (self.n,):
            raise ValueError("predicate must return one boolean per particle")
        return mask


COORDINATE_LIMIT = 1e100  # squared bond lengths and volumes h^dim stay inside float64


def _refuse_duplicates(x: np.ndarray, h: float) -> None:
    """Particles closer than 1e-6 h are one point given twice (their bond would be ~0 long)."""
    close = cKDTree(x).query_pairs(1e-6 * h, output_type="ndarray")
    if len(close):
        i, j = close[0]
        raise ValueError(f"{len(close)} pair(s) of particles are closer than 1e-6 h = {1e-6 * h:g} (e.g. {i} "
                         f"at {x[i].tolist()} and {j} at {x[j].tolist()}): remove duplicate points")


def _cell_centres(extent, h: float, origin) -> np.ndarray:
    """Centres of a regular grid of cubic cells of size h filling a box of the given extent."""
    positive("h", h)
    positive("the box extents", list(extent))
    if any(e / h > 1e7 for e in extent):
        raise ValueError(f"h={h:g} cuts the box {list(extent)} into more than 1e7 cells along an axis: "
                         "check the units of h and the extents")
    counts = [round(e / h) for e in extent]
    if any(abs(c * h - e) > 1e-9 * e for c, e in zip(counts, extent)):
        raise ValueError(f"every extent of the box must be a multiple of h={h}")
    axes = [o + h * (np.arange(c) + 0.5) for o, c in zip(origin, counts)]
    return np.stack(np.meshgrid(*axes, indexing="xy"), axis=-1).reshape(-1, len(extent))


def grid_2d(length: float, width: float, h: float, thickness: float = 1.0,
            origin=(0.0, 0.0)) -> Particles:
    """Cell-centred regular grid filling [0, length] x [0, width] (shifted by ``origin``)."""
    positive("the thickness", thickness)
    x = _cell_centres((length, width), h, origin)
    return Particles(x, np.full(len(x), h * h * thickness), h, thickness)


def grid_3d(length: float, width: float, depth: float, h: float, origin=(0.0, 0.0, 0.0)) -> Particles:
    """Cell-centred cubic grid filling [0, length] x [0, width] x [0, depth] (+ ``origin``)."""
    x = _cell_centres((length, width, depth), h, origin)
    return Particles(x, np.full(len(x), h**3), h)


def from_points(x, volume, h: float | None = None, thickness: float = 1.0) -> Particles:
    """Particles at arbitrary positions ``x`` (N, dim) with cell volumes ``volume`` (N,).

    ``h`` (the spacing used by the partial-volume rule) defaults to the cube (3D) or square
    (2D, volume / thickness) root of the median cell volume.
    """
    x, volume = np.asarray(x, dtype=float), np.asarray(volume, dtype=float)
    if x.ndim != 2 or x.shape[1] not in (2, 3) or len(x) == 0:
        raise ValueError(f"x must be a non-empty (N, 2) or (N, 3) array, got shape {x.shape}")
    if volume.shape != (len(x),):
        raise ValueError(f"volume must have one entry per particle ({len(x)}), got {volume.shape}")
    h = h or float(np.abs(np.median(volume) / thickness) ** (1 / x.shape[1]))
    return Particles(x, volume, float(h), thickness)  # checks NaN, volumes and duplicates
