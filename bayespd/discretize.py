"""Particles: reference positions ``x``, volumes, grid spacing ``h`` and thickness (2D)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Particles:
    """A set of particles (EMU nodal discretisation, seed 001 §2.2.4).

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
        if not (self.h > 0 and self.thickness > 0):
            raise ValueError("h and thickness must be positive")

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


def grid_2d(length: float, width: float, h: float, thickness: float = 1.0,
            origin=(0.0, 0.0)) -> Particles:
    """Cell-centred regular grid filling [0, length] x [0, width] (shifted by ``origin``)."""
    if not (length > 0 and width > 0 and h > 0):
        raise ValueError("length, width and h must be positive")
    nx, ny = round(length / h), round(width / h)
    if abs(nx * h - length) > 1e-9 * length or abs(ny * h - width) > 1e-9 * width:
        raise ValueError(f"length and width must be multiples of h={h}")
    gx = origin[0] + h * (np.arange(nx) + 0.5)
    gy = origin[1] + h * (np.arange(ny) + 0.5)
    x = np.stack(np.meshgrid(gx, gy, indexing="xy"), axis=-1).reshape(-1, 2)
    return Particles(x, np.full(len(x), h * h * thickness), h, thickness)
