"""A plate with a central hole in tension (the demo's plate) as a PD scene and its FE peer.

Plate L x W x t = 40 x 20 x 1 mm, origin at the bottom-left corner, hole of radius R = 4 mm at
the centre, plane stress. The left layer x <= ``clamp`` (6 mm) is clamped (a PD Dirichlet layer
a horizon thick; the FE peer fixes every node in the same volume, i.e. clamps the face x = 6);
F = 200 N along +x is spread as a uniform body force over the right layer x >= L - 2 mm in both
models. :class:`Geometry` changes the dimensions (the tests use a long plate, whose stress
concentration has a classical value).

FE mesh (:func:`hole_mesh`): an O-grid of four sectors between the hole and the square of
half-side W / 2 around it (each node on the segment from the hole, at the square's polar angle,
to the square, graded toward the hole as t^1.5), and tensor-product blocks left and right of it,
graded toward the clamp's corners (singular, as in ``three_point_bending``). The hole is the
polygon through the nodes on the circle: with 4 W / h sides its sagitta is below 1e-3 R at h = 1.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import bayespd as bp
from bayespd.reference.fem import BodyLoad, FESolution, Region, Support, graded_axis, require_skfem, solve_mesh


@dataclass(frozen=True)
class Geometry:
    """Dimensions (mm) and load (N) of the plate; the hole sits at the centre."""

    length: float = 40.0
    width: float = 20.0
    radius: float = 4.0
    thickness: float = 1.0
    clamp: float = 6.0
    load_depth: float = 2.0
    force: float = 200.0

    def __post_init__(self):
        if not 0 < self.radius < self.width / 2 or self.length / 2 - self.width / 2 <= self.clamp:
            raise ValueError("the hole must fit in the plate and the clamp must end left of the square of "
                             "half-side width / 2 around the hole: shrink radius or clamp, or lengthen the plate")

    @property
    def centre(self) -> np.ndarray:
        return np.array([self.length / 2, self.width / 2])

    @property
    def clamped(self) -> Region:
        return Region((0.0, 0.0), (self.clamp, self.width))

    @property
    def loaded(self) -> Region:
        return Region((self.length - self.load_depth, 0.0), (self.length, self.width))

    def nominal_stress(self) -> float:
        """F / (W t): the gross-section stress far from the hole."""
        return self.force / (self.width * self.thickness)


PLATE = Geometry()
YOUNG, POISSON = 4000.0, 0.3  # MPa, -


def params(delta: float, young: float = YOUNG, nu: float = POISSON) -> dict:
    """PD params {K, G, delta} (K the 3D bulk modulus, as bp.LPS takes it in plane stress)."""
    K, G = bp.moduli_from_young(young, nu)
    return {"K": float(K), "G": float(G), "delta": float(delta)}


def pd_scene(h: float, delta_max: float, points=None, rule: str = "linear", geometry: Geometry = PLATE,
             **lps_options) -> bp.Scene:
    """LPS plane-stress scene on a cell-centred grid of spacing h without the hole's cells."""
    g = geometry
    p = bp.grid_2d(g.length, g.width, h, thickness=g.thickness)
    p = p.where(np.linalg.norm(p.x - g.centre, axis=1) > g.radius)
    material = bp.LPS(p, bp.find_bonds(p, delta_max, rule), plane="stress", **lps_options)
    observation = None if points is None else bp.Observation(p, points)
    return bp.Scene(material, [bp.Dirichlet(g.clamped.contains(p.x), (0.0, 0.0))],
                    [bp.Load(g.loaded.contains(p.x), (g.force, 0.0))], observation)


def _sector(g: Geometry, s: np.ndarray, t: np.ndarray, turn: int) -> np.ndarray:
    """Nodes (len(t), len(s), 2) of the O-grid sector facing +x rotated by ``turn`` quarter turns."""
    a = g.width / 2
    c, sn = np.cos(turn * np.pi / 2), np.sin(turn * np.pi / 2)
    rot = np.array([[c, -sn], [sn, c]])
    square = np.stack([np.full_like(s, a), s], axis=1) @ rot.T
    phi = np.arctan2(s, a)
    circle = g.radius * np.stack([np.cos(phi), np.sin(phi)], axis=1) @ rot.T
    return g.centre + circle[None] + t[:, None, None] * (square - circle)[None]


def _quads(nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 2) and quads (4, m) of a structured block of nodes (n0, n1, 2)."""
    n0, n1 = nodes.shape[:2]
    ids = np.arange(n0 * n1).reshape(n0, n1)
    quads = np.stack([ids[:-1, :-1], ids[1:, :-1], ids[1:, 1:], ids[:-1, 1:]]).reshape(4, -1)
    return nodes.reshape(-1, 2), quads


def hole_mesh(h: float, geometry: Geometry = PLATE, grading: int = 4):
    """The MeshQuad1 of the module docstring with nominal size h (h must divide clamp, the
    blocks' widths, the load depth and W / 2)."""
    skfem = require_skfem()
    g = geometry
    a, (cx, cy) = g.width / 2, g.centre
    for name, v in (("clamp", g.clamp), ("left block", cx - a), ("load depth", g.load_depth), ("W / 2", a)):
        if abs(v / h - round(v / h)) > 1e-9 * max(1.0, v / h):
            raise ValueError(f"mesh size h={h} must divide the {name} ({v} mm): pick another h")
    y = graded_axis(g.width, h, (0.0, g.width), grading)
    x_left = graded_axis(cx - a, h, (g.clamp,), grading)
    x_right = cx + a + graded_axis(g.length - cx - a, h)
    across = np.linspace(-a, a, round(2 * a / h) + 1)
    n_r = max(2, int(np.ceil((a - g.radius) / h)))
    t = (np.arange(n_r + 1) / n_r) ** 1.5
    blocks = [np.stack(np.meshgrid(x_left, y, indexing="ij"), -1), np.stack(np.meshgrid(x_right, y, indexing="ij"), -1)]
    blocks += [_sector(g, y - cy if turn % 2 == 0 else across, t, turn) for turn in range(4)]
    points, cells, offset = [], [], 0
    for nodes in blocks:
        p, q = _quads(nodes)
        points.append(p)
        cells.append(q + offset)
        offset += len(p)
    points, cells = np.concatenate(points), np.concatenate(cells, axis=1)
    key = np.round(points / (1e-9 * g.length)).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    points, cells = points[first], inverse.reshape(-1)[cells]
    p0, p1, p3 = (points[cells[k]] for k in (0, 1, 3))
    e1, e3 = p1 - p0, p3 - p0
    flip = e1[:, 0] * e3[:, 1] - e1[:, 1] * e3[:, 0] < 0  # make every quad counter-clockwise
    cells[:, flip] = cells[::-1][:, flip]
    return skfem.MeshQuad1(np.ascontiguousarray(points.T), np.ascontiguousarray(cells))


REFERENCE_MESH = {"h": 0.5, "order": 2, "grading": 4}


def fe_solution(h: float = 0.5, order: int = 2, grading: int = 4, young: float = YOUNG, nu: float = POISSON,
                geometry: Geometry = PLATE, stiffness=None) -> FESolution:
    """The FE peer (plane stress, Q``order`` on :func:`hole_mesh`): the same clamp and load."""
    g = geometry
    return solve_mesh(hole_mesh(h, g, grading), young, nu, [Support(g.clamped, (0.0, 0.0))],
                      [BodyLoad(g.loaded, (g.force, 0.0))], order=order, plane="stress",
                      thickness=g.thickness, stiffness=stiffness, h=h)


def away_mask(x: np.ndarray, margin: float, geometry: Geometry = PLATE) -> np.ndarray:
    """Points farther than ``margin`` from the clamp and the loaded layer."""
    return np.minimum(geometry.clamped.distance(x), geometry.loaded.distance(x)) > margin


def hole_stress(fe: FESolution, young: float = YOUNG, geometry: Geometry = PLATE, angle: float = np.pi / 2,
                step: float = 1e-4) -> float:
    """The hoop stress sigma_tt = E eps_tt at the hole's edge at polar ``angle`` of an isotropic
    plane-stress FE field (the free surface leaves the stress there uniaxial), with eps_tt =
    (d u_t / d theta + u_r) / R by central differences on the circle."""
    g = geometry
    theta = angle + np.array([-step, 0.0, step])
    r = g.radius * (1 + 1e-9)
    u = fe.at(g.centre + r * np.stack([np.cos(theta), np.sin(theta)], axis=1))
    radial = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    tangent = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
    u_t, u_r = (u * tangent).sum(1), (u * radial).sum(1)
    return young * ((u_t[2] - u_t[0]) / (2 * step) + u_r[1]) / g.radius
