"""Finite-element reference solutions of small-strain linear elasticity (scikit-fem).

Classical peer of the peridynamic scenes: the PD model converges, as delta -> 0, to the local
problem with the *same* volume constraints and body forces (Delorme 2018 eq 11: loads ``b`` on
the layer V_f, displacements prescribed on the layer V_u). So the FE problem here is posed on
a box, with displacements fixed on sub-boxes (volumes, not points) and each load spread as a
uniform body force over a sub-box. Meshes are tensor-product Q1/Q2 (quads in 2D, hexes in 3D)
aligned with every sub-box, so the constraint and load regions are represented exactly.

scikit-fem is a development dependency: it is imported inside the functions only.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch

from bayespd.linalg.amg import rigid_body_modes, v_cycle
from bayespd.linalg.config import choose_solver
from bayespd.linalg.sparse import Pattern, PCGFactor, default_backend, splu_factor


def require_skfem():
    """Import scikit-fem, or say how to install it."""
    try:
        import skfem
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("the finite-element reference needs scikit-fem: "
                          "pip install scikit-fem (or pip install -e '.[dev]')") from e
    return skfem


@dataclass(frozen=True)
class Region:
    """A closed axis-aligned box [lo, hi] (a support patch, clamp or load layer)."""

    lo: tuple
    hi: tuple

    def contains(self, x: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Mask of the points ``x`` (N, dim) inside the closed box."""
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        return np.all((x >= lo - tol) & (x <= hi + tol), axis=-1)

    def distance(self, x: np.ndarray) -> np.ndarray:
        """Euclidean distance of each point to the box (0 inside)."""
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        return np.linalg.norm(np.maximum(np.maximum(lo - x, x - hi), 0.0), axis=-1)

    @property
    def measure(self) -> float:
        return float(np.prod(np.asarray(self.hi, float) - np.asarray(self.lo, float)))


@dataclass(frozen=True)
class Support:
    """Displacement components fixed to zero on a region (``None`` = free, as in bp.Dirichlet)."""

    region: Region
    value: tuple


@dataclass(frozen=True)
class BodyLoad:
    """A total force spread uniformly over the volume of a region (as bp.Load on a grid)."""

    region: Region
    force: tuple


class FESolution:
    """A solved FE field: ``at(points)`` evaluates u (n, dim) by the element basis."""

    def __init__(self, basis, axes, u: np.ndarray, h: float, order: int, wall_time_s: float):
        self.basis, self.axes, self.u, self.h, self.order = basis, axes, u, h, order
        self.wall_time_s = wall_time_s
        self.dim = basis.mesh.dim()

    @property
    def n_dofs(self) -> int:
        return int(self.basis.N)

    def at(self, points: np.ndarray) -> np.ndarray:
        """Displacement (n, dim) at ``points`` (n, dim) inside the mesh."""
        points = np.atleast_2d(np.asarray(points, dtype=float))
        values = probe_matrix(self.basis, self.axes, points) @ self.u
        return values.reshape(self.dim, len(points)).T


def probe_matrix(basis, axes: list[np.ndarray] | None, points: np.ndarray):
    """Sparse matrix evaluating a vector FE field at ``points`` (rows: component-major).

    Same construction as skfem's ``CellBasis.probes``, but the cell of each point comes
    from the tensor-product ``axes`` in O(log n) (skfem's generic finder is quadratic in
    memory), or, on an unstructured mesh (``axes=None``), from the nearest cell centres.
    """
    from scipy.sparse import coo_matrix

    cells = _cells_on_axes(basis.mesh, axes, points) if axes is not None else _cells_near(basis, points)
    local = basis.mapping.invF(points.T[:, :, None], tind=cells)
    phis = np.array([basis.elem.gbasis(basis.mapping, local, k, tind=cells)[0]
                     for k in range(basis.Nbfun)]).flatten()
    comp = points.shape[1]
    rows = np.tile(np.arange(comp * len(points)), basis.Nbfun)
    cols = basis.element_dofs[:, np.tile(cells, comp)].flatten()
    return coo_matrix((phis, (rows, cols)), shape=(comp * len(points), basis.N)).tocsr()


def _cells_on_axes(mesh, axes, points):
    if np.any(points < [a[0] for a in axes]) or np.any(points > [a[-1] for a in axes]):
        raise ValueError("a probe point lies outside the FE box")
    corner = mesh.p[:, mesh.t].min(axis=1)  # (dim, n_cells): each cell's lowest corner
    shape = [len(a) - 1 for a in axes]
    ids = [np.searchsorted(a, c) for a, c in zip(axes, corner)]
    lookup = np.empty(shape, dtype=np.int64)
    lookup[tuple(ids)] = np.arange(mesh.t.shape[1])
    idx = [np.clip(np.searchsorted(a, x, side="right") - 1, 0, n - 1)
           for a, x, n in zip(axes, points.T, shape)]
    return lookup[tuple(idx)]


def _cells_near(basis, points, candidates: int = 8):
    """The cell of each point on a 2D mesh of straight-edged convex quads: the first of its
    nearest cell centres whose counter-clockwise edges all have the point on their left."""
    from scipy.spatial import cKDTree

    mesh = basis.mesh
    if mesh.dim() != 2 or mesh.t.shape[0] != 4:
        raise ValueError("probes off a tensor-product mesh are implemented for 2D quad meshes only")
    corners = mesh.p[:, mesh.t]  # (2, 4, n_cells), counter-clockwise
    near = cKDTree(corners.mean(axis=1).T).query(points, k=min(candidates, mesh.t.shape[1]))[1]
    near = near.reshape(len(points), -1)
    cells = np.full(len(points), -1)
    for k in range(near.shape[1]):
        c = corners[:, :, near[:, k]]
        edge, rel = np.roll(c, -1, axis=1) - c, points.T[:, None, :] - c
        cross = edge[0] * rel[1] - edge[1] * rel[0]  # (4, n)
        tol = 1e-9 * (edge**2).sum(axis=0)
        inside = (cells < 0) & np.all(cross >= -tol, axis=0)
        cells[inside] = near[inside, k]
    if np.any(cells < 0):
        raise ValueError(f"{int((cells < 0).sum())} probe point(s) lie outside the FE mesh "
                         f"(e.g. {points[cells < 0][0].tolist()})")
    return cells


def graded_axis(length: float, h: float, at=(), levels: int = 0) -> np.ndarray:
    """Nodes h apart on [0, length], plus nodes at s +- h 2^-k (k = 1..levels) around each
    s in ``at``: geometric grading toward the lines through singular corners."""
    n = round(length / h)
    if abs(n * h - length) > 1e-9 * length:
        raise ValueError(f"mesh size h={h} must divide the box extent {length}")
    nodes = [np.linspace(0.0, length, n + 1)]
    for s in at:
        offsets = h * 0.5 ** np.arange(1, levels + 1)
        nodes.append(np.concatenate([s - offsets, s + offsets]))
    x = np.unique(np.round(np.concatenate(nodes), 12))
    return x[(x >= 0) & (x <= length)]


def _check_aligned(region: Region, h: float) -> None:
    for v in (*region.lo, *region.hi):
        if abs(v / h - round(v / h)) > 1e-9 * max(1.0, abs(v / h)):
            raise ValueError(f"region {region} is not aligned with the mesh size h={h}: "
                             "pick h dividing every region corner")


def spd_solve(A, b: np.ndarray, modes: np.ndarray | None = None) -> np.ndarray:
    """Solve a sparse SPD system with bayespd's backend (CHOLMOD when installed, else SuperLU);
    a 3D system (``modes``: its 6 rigid-body modes) where ``linalg.choose_solver`` says so by
    PCG with the AMG V-cycle to a relative residual of 1e-10: SuperLU's factor of the 3D
    cantilever's Q2 mesh grew past 4 GB (AMG: 241 iterations, 28 s, 1.9 GB peak). 2D systems
    stay direct: SuperLU factorises the beam's 200k-dof Q2 mesh in seconds, where its graded
    cells cost AMG 386 iterations (21 s; benchmarks/README.md, issue 31). The cycle keeps
    pyamg's Gauss-Seidel: the two-thread l1 hybrid one (``linalg.row_runs``), made for PD bond
    operators, took 406 iterations on the cantilever's Q2 stiffness against 241 (25.2 s against
    23.8 s: its l1 pivots weaken the sweep where a Q2 row's couplings outweigh its diagonal)."""
    A = sp.csr_matrix(A)  # no copy of solve_mesh's CSR: SuperLU's fill alone sets the peak
    A.sum_duplicates()
    A.sort_indices()
    if modes is not None and modes.shape[1] == 6 and choose_solver(A.shape[0], 3, default_backend()) == "amg":
        return PCGFactor(A.__matmul__, v_cycle(A, modes, hybrid=False), A.shape[0], rtol=1e-10).solve(b)
    if default_backend() == "splu":  # A is symmetric: its CSR arrays are its CSC arrays
        return splu_factor(sp.csc_matrix((A.data, A.indices, A.indptr), shape=A.shape)).solve(b)
    A = A.tocsc()
    cols = np.repeat(np.arange(A.shape[1]), np.diff(A.indptr))
    pattern = Pattern(A.indices.astype(np.int64), cols.astype(np.int64), A.shape[0])
    factor = pattern.factorize(torch.as_tensor(A.data))
    return np.asarray(factor.solve(b)).reshape(-1)


VOIGT = {2: [(0, 0), (1, 1), (0, 1)], 3: [(0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1)]}
"""Voigt order of the strain components (shear entries are engineering strains 2 eps_ab)."""


def isotropic_stiffness(E: float, nu: float, dim: int, plane: str | None = "stress") -> np.ndarray:
    """Voigt stiffness of an isotropic solid: 3D, or 2D plane stress / plane strain."""
    mu = E / (2 * (1 + nu))
    if dim == 2 and plane == "stress":
        lam = E * nu / (1 - nu**2)  # lambda* of the plane-stress reduction
    elif dim == 3 or plane == "strain":
        lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    else:
        raise ValueError("plane must be 'stress' or 'strain' in 2D")
    C = np.zeros((len(VOIGT[dim]),) * 2)
    C[:dim, :dim] = lam
    C[:dim, :dim] += 2 * mu * np.eye(dim)
    C[dim:, dim:] = mu * np.eye(len(VOIGT[dim]) - dim)
    return C


CHUNK_ENTRIES = 1_000_000
"""Element-matrix entries assembled at a time (cells x local dofs^2): a 3D Q2 cell has 81^2,
and the quadrature data of 2,000 of them set the peak memory of the cantilever's reference
solve (benchmarks/README.md, issue 31)."""


def _chunks(n: int, size: int):
    return [np.arange(k, min(n, k + size)) for k in range(0, n, size)]


def solve_box(extent, h: float, E: float, nu: float, supports: list[Support],
              loads: list[BodyLoad], order: int = 2, plane: str | None = "stress",
              thickness: float = 1.0, grading: int = 0, stiffness=None,
              chunk: int | None = None) -> FESolution:
    """Linear elasticity on [0, extent] with Q``order`` elements of size ``h``.

    2D (plane stress/strain, thickness ``thickness``) when ``extent`` has two entries, 3D with
    three. ``stiffness`` (Voigt, see ``VOIGT``) replaces the isotropic (E, nu) tensor, e.g. by
    the effective anisotropic tensor of a PD lattice. Every dof located in a support region
    gets its fixed components set to zero; each load is a body force F / (|region| t) on its
    region. ``grading`` levels of geometric refinement go toward the support faces, where the
    corners of a fixed region are stress singularities (r^lambda, lambda < 1) that otherwise
    pollute the whole field and slow convergence to O(h^(2 lambda)). Assembly runs over
    ``chunk`` elements at a time (None: ``CHUNK_ENTRIES`` element-matrix entries) to bound the
    memory of the quadrature data.
    """
    skfem = require_skfem()
    start = time.perf_counter()
    dim = len(extent)
    if dim not in (2, 3) or order not in (1, 2):
        raise ValueError("solve_box handles 2D/3D boxes with order 1 or 2")
    for r in [s.region for s in supports] + [ld.region for ld in loads]:
        _check_aligned(r, h)
    faces = [{v for s in supports for v in (s.region.lo[a], s.region.hi[a])} for a in range(dim)]
    axes = [graded_axis(e, h, sorted(f), grading) for e, f in zip(extent, faces)]
    mesh = skfem.MeshQuad1.init_tensor(*axes) if dim == 2 else skfem.MeshHex1.init_tensor(*axes)
    return solve_mesh(mesh, E, nu, supports, loads, order=order, plane=plane, thickness=thickness,
                      stiffness=stiffness, chunk=chunk, axes=axes, h=h, start=start)


def solve_mesh(mesh, E: float, nu: float, supports: list[Support], loads: list[BodyLoad], *,
               order: int = 2, plane: str | None = "stress", thickness: float = 1.0, stiffness=None,
               chunk: int | None = None, axes=None, h: float | None = None, start: float | None = None) -> FESolution:
    """Linear elasticity with Q``order`` elements on a quad (2D) or hex (3D) ``mesh`` (see
    :func:`solve_box` for the supports, loads and ``stiffness``; the support and load regions
    must be unions of cells). ``axes``: the mesh's tensor-product axes when it has them (fast
    probes); ``h``: the nominal mesh size recorded in the solution."""
    skfem = require_skfem()
    from skfem.helpers import sym_grad

    start = time.perf_counter() if start is None else start
    dim = mesh.dim()
    if order not in (1, 2) or not isinstance(mesh, (skfem.MeshQuad1, skfem.MeshHex1)):
        raise ValueError("solve_mesh takes a MeshQuad1 or MeshHex1 and order 1 or 2")
    C = isotropic_stiffness(E, nu, dim, plane) if stiffness is None else np.asarray(stiffness, float)
    if C.shape != (len(VOIGT[dim]),) * 2 or not np.allclose(C, C.T):
        raise ValueError(f"stiffness must be a symmetric {len(VOIGT[dim])}x{len(VOIGT[dim])} Voigt matrix")
    if dim == 3:
        thickness = 1.0
    if dim == 2:
        elem = skfem.ElementQuad1() if order == 1 else skfem.ElementQuad2()
    else:
        elem = skfem.ElementHex1() if order == 1 else skfem.ElementHex2()
    elem = skfem.ElementVector(elem)
    X, W = skfem.quadrature.get_quadrature(elem.refdom, 1)
    # dofs, dof locations and probes only: one quadrature point, the least data kept per cell
    basis = skfem.Basis(mesh, elem, quadrature=(X[:, :1], W[:1]))
    entries = [(i, j, C[i, j]) for i in range(len(C)) for j in range(len(C)) if C[i, j] != 0]

    def voigt(eps):
        return [eps[a, b] if a == b else 2 * eps[a, b] for a, b in VOIGT[dim]]

    @skfem.BilinearForm
    def energy(u, v, w):
        eu, ev = voigt(sym_grad(u)), voigt(sym_grad(v))
        return sum(c * eu[j] * ev[i] for i, j, c in entries)

    @skfem.LinearForm
    def body(v, w):
        f = 0.0
        for ld in loads:  # quadrature points never lie on the aligned region faces
            inside = ld.region.contains(np.moveaxis(w.x, 0, -1), tol=0.0)
            density = np.asarray(ld.force, float) / (ld.region.measure * thickness)
            f = f + sum(inside * density[c] * v[c] for c in range(dim))
        return f

    comps = basis.split_indices()
    fixed = []
    for s in supports:
        if len(s.value) != dim:
            raise ValueError(f"support value needs {dim} components (None = free)")
        for c, v in enumerate(s.value):
            if v is not None:
                if v != 0:
                    raise ValueError("solve_mesh fixes components to zero only")
                idx = comps[c]
                fixed.append(idx[s.region.contains(basis.doflocs[:, idx].T)])
    D = np.unique(np.concatenate(fixed)) if fixed else np.array([], dtype=np.int64)
    if len(D) == 0:
        raise ValueError("no dof lies in the support regions: the problem is singular")
    free = np.setdiff1d(np.arange(basis.N), D)
    chunk = chunk or max(1, CHUNK_ENTRIES // basis.Nbfun**2)
    A, b = 0, 0
    for cells in _chunks(mesh.t.shape[1], chunk):  # each part restricted to the free dofs at once
        part = skfem.Basis(mesh, elem, intorder=2 * order, elements=cells, dofs=basis.dofs,
                           disable_doflocs=True)
        A = A + energy.assemble(part)[free][:, free]
        b = b + body.assemble(part)[free]
        del part
    u = np.zeros(basis.N)
    component = np.empty(basis.N, dtype=np.int64)
    for c, idx in enumerate(comps):
        component[idx] = c
    modes = rigid_body_modes(basis.doflocs.T, component)[free]
    u[free] = spd_solve(A, b, modes)
    return FESolution(basis, axes, u, h, order, time.perf_counter() - start)
