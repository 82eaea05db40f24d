"""Reliability under bad and extreme input (issue 27): a catalogue of >= 150 cases through the
API and the CLI -- Scene parts (Dirichlet values, loads, load factors, moduli, delta, grids,
particles, pre-cracks), observations, file readers fed missing, empty, truncated, binary and
garbage files, fit settings of every method, data of wrong types and shapes, priors, CLI
invocations with bad arguments and files, the stability suite's extreme cases, and the
kill/resume checks (NUTS through the API with a SIGKILLed chain worker, the CLI SIGKILLed,
checkpoints refusing changed data and a changed prior, a crack ensemble SIGKILLed and resumed).

Each case runs in a forked worker process under a time limit (past it: ``hang``; the worker is
killed and a fresh one forked) and is classified:

* ``refused``: a ValueError / TypeError / FileNotFoundError, or an error class defined in
  bayespd, raised from a frame inside the bayespd package, whose message names the parameter
  or file (one of the case's words); for the CLI, a non-zero exit whose stderr names it and
  holds no traceback;
* ``handled``: a finite result that passes the case's own physical check;
* ``silent_wrong``: a result with NaN/inf or failing its check;
* ``raw_exception``: the rule -- any other exception: one raised inside a dependency (torch,
  pyro, scipy, h5py, numpy, ...) that no bayespd frame translated (its innermost frame is not
  bayespd's), an exception class outside the three above, or a bayespd message that names
  none of the case's words; for the CLI, a traceback on stderr;
* ``hang``: no answer within the case's limit.

Writes runs/reliability/metrics.json (counts per outcome, every case with its outcome, detail
and time; targets: 0 silent_wrong, 0 hang, 0 raw_exception, kill/resume bit-identical) and
prints one line per case.

    python experiments/reliability.py [--quick]    # --quick: a subset, < 2 minutes
"""
from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
import traceback
import warnings
from functools import cache
from pathlib import Path

import numpy as np
import torch

import common  # noqa: F401  (one torch thread, repository root on sys.path)
from common import ROOT, write_metrics

import bayespd as bp

PACKAGE = Path(bp.__file__).resolve().parent
NAN, INF = math.nan, math.inf
OUTCOMES = ("refused", "handled", "silent_wrong", "raw_exception", "hang")
CASES: list[dict] = []
TMP = Path(tempfile.mkdtemp(prefix="reliability-"))
ENV = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONWARNINGS="ignore")


def add(name, group, fn, *names, timeout=60, quick=False):
    """One case: ``fn()`` returns (ok, detail) for a result, or raises; ``names``: the words one of
    which a refusal must name."""
    assert name not in {c["name"] for c in CASES}, name
    CASES.append(dict(name=name, group=group, fn=fn, names=names, timeout=timeout, quick=quick))


def finite_check(u, extra=True, detail=""):
    u = torch.as_tensor(u)
    ok = bool(torch.isfinite(u).all()) and bool(extra)
    return ok, detail or f"finite={bool(torch.isfinite(u).all())}, max |value| {float(u.abs().max()):.3g}"


# --- scenes, built once (before the worker forks) ----------------------------------------------

@cache
def plate():
    p = bp.grid_2d(10.0, 6.0, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 2.5))
    scene = bp.Scene(mat, [bp.Dirichlet.layer(p, "left", 2.5)], [bp.Load(p.layer("right", 1.0), (30.0, 10.0))],
                     bp.Observation(p, p.x[~p.layer("left", 2.5)]))
    return p, mat, scene


PARAMS = {"K": 1000.0, "G": 600.0, "delta": 2.0}


@cache
def unit_u():
    return plate()[2].solve(PARAMS)


def solve(**change):
    return plate()[2].solve(dict(PARAMS, **change))


def scene_with(dirichlet=None, loads=None, **kw):
    p, mat, scene = plate()
    return bp.Scene(mat, scene.dirichlet if dirichlet is None else dirichlet,
                    scene.loads if loads is None else loads, scene.observation, **kw)


def linear_in_factor(factor):
    u = solve(load=factor)
    ok = bool(torch.isfinite(u).all()) and torch.allclose(u, factor * unit_u(), rtol=1e-9,
                                                         atol=max(1e-12 * abs(factor), 1e-290))
    return ok, f"u = {factor:g} u(1): {ok}"


def scales_as_one_over_K(K):
    u = solve(K=K, G=0.6 * K)
    ok = bool(torch.isfinite(u).all()) and torch.allclose(u * (K / 1000.0), unit_u(), rtol=1e-7, atol=1e-300)
    return ok, f"u K = const: {ok}"


def load_case(force):
    p = plate()[0]
    s = scene_with(loads=[bp.Load(p.layer("right", 1.0), force)])
    u = s.solve(PARAMS)
    work = float(((u / u.abs().max()) * (s.force / s.force.abs().max())).sum())
    return finite_check(u, work > 0, f"finite, work f.u > 0: {work > 0}")


def _subnormal_load():
    p = plate()[0]
    u = scene_with(loads=[bp.Load(p.layer("right", 1.0), (5e-324, 0.0))]).solve(PARAMS)
    u1 = scene_with(loads=[bp.Load(p.layer("right", 1.0), (1.0, 0.0))]).solve(PARAMS)
    gap = float((u - 5e-324 * u1).abs().max())
    return finite_check(u, gap <= 1e-300, f"|u - f u(1)| = {gap:.3g} (subnormal range)")


def dirichlet_case(value):
    p = plate()[0]
    s = scene_with(dirichlet=[plate()[2].dirichlet[0], bp.Dirichlet.layer(p, "right", 2.5, value)], loads=[])
    u = s.solve(PARAMS)
    right = p.layer("right", 2.5)
    ok = bool(torch.isfinite(u).all()) and np.allclose(u[right, 0].numpy(), value[0])
    return ok, f"finite and the layer at its value: {ok}"


# --- Scene parts ------------------------------------------------------------------------------

def scene_cases():
    P = lambda: plate()[0]
    for v in (NAN, INF, -INF):
        add(f"dirichlet value x={v}", "scene", lambda v=v: bp.Dirichlet(P().layer("left", 2.5), (v, 0.0)),
            "dirichlet value", quick=True)
        add(f"dirichlet value y={v} with x free", "scene", lambda v=v: bp.Dirichlet(P().layer("left", 2.5), (None, v)),
            "dirichlet value")
    add("dirichlet value a string", "scene", lambda: bp.Dirichlet(P().layer("left", 2.5), ("a", 0.0)),
        "dirichlet value", "numbers")
    add("dirichlet 3 components in 2D", "scene", lambda: scene_with(dirichlet=[bp.Dirichlet(P().layer("left", 2.5), (0, 0, 0))]),
        "dirichlet value")
    add("dirichlet empty mask", "scene", lambda: bp.Dirichlet(np.zeros(P().n, bool)), "dirichlet region")
    add("no dirichlet region", "scene", lambda: scene_with(dirichlet=[]), "dirichlet")
    add("zero dirichlet and no load", "scene", lambda: scene_with(loads=[]), "nothing loads", quick=True)
    for v in (1e-300, 1e-3, 1e100):
        add(f"dirichlet pull {v:g} (linear)", "scene", lambda v=v: dirichlet_case((v, 0.0)), "dirichlet", "displacement")
    add("dirichlet pull 1e308 (overflow)", "scene", lambda: dirichlet_case((1e308, 0.0)), "dirichlet", "displacement")
    for f in ((NAN, 0.0), (INF, 0.0), (0.0, -INF)):
        add(f"load {f}", "scene", lambda f=f: bp.Load(P().layer("right", 1.0), f), "load", quick=True)
    add("load of 3 components in 2D", "scene", lambda: scene_with(loads=[bp.Load(P().layer("right", 1.0), (1.0, 0, 0))]),
        "force", "component")
    add("load a string", "scene", lambda: bp.Load(P().layer("right", 1.0), "ab"), "load", "numbers", "force")
    add("load empty region", "scene", lambda: bp.Load(np.zeros(P().n, bool), (1.0, 0.0)), "load region")
    add("load on the clamped layer", "scene", lambda: scene_with(loads=[bp.Load(P().layer("left", 1.0), (1.0, 0.0))]),
        "load 0", "dirichlet", quick=True)
    add("zero load, zero dirichlet", "scene", lambda: scene_with(loads=[bp.Load(P().layer("right", 1.0), (0.0, 0.0))]),
        "nothing loads")
    for f in ((1e-300, 0.0), (1e100, -1e100), (1e300, 1e300)):
        add(f"load {f} (finite solve)", "scene", lambda f=f: load_case(f), "load", "displacement")
    add("load (5e-324, 0) (subnormal: u = f u(1))", "scene", lambda: _subnormal_load(), "load", "nothing loads")
    add("load mask of wrong length", "scene", lambda: scene_with(loads=[bp.Load(np.ones(3, bool), (1.0, 0.0))]),
        "load", "mask", "region")
    for k in (NAN, INF, -INF, "x"):
        add(f"load factor {k}", "scene", lambda k=k: solve(load=k), "load factor", quick=k is NAN)
    for k in (0.0, -2.0, 1e-300, 1e200):
        add(f"load factor {k:g} (linear)", "scene", lambda k=k: linear_in_factor(k), "load")
    add("load factor 1e308 (overflow)", "scene", lambda: linear_in_factor(1.7e308), "load")
    for K in (NAN, INF, -1.0, 0.0, 1e-300, 1e200, 5e-324):
        add(f"K={K:g}", "moduli", lambda K=K: solve(K=K), "K", quick=K in (NAN, 0.0))
    for G in (NAN, -5.0, 0.0):
        add(f"G={G:g}", "moduli", lambda G=G: solve(G=G), "G")
    for K in (1e-90, 1e-3, 1e90):
        add(f"K={K:g} (u ~ 1/K)", "moduli", lambda K=K: scales_as_one_over_K(K), "K")
    add("K a string", "moduli", lambda: solve(K="soft"), "K", "numbers")
    add("K field of wrong length", "moduli", lambda: solve(K=torch.ones(3)), "K", "per particle")
    add("K field with one NaN", "moduli", lambda: solve(K=torch.full((60,), 1000.0).index_fill(0, torch.tensor([7]), NAN)), "K")
    add("K field with contrast 1e6", "moduli",
        lambda: finite_check(solve(K=torch.where(torch.arange(60) < 30, 1e3, 1e9), G=600.0)), "K")
    add("missing G", "moduli", lambda: plate()[2].solve({"K": 1.0, "delta": 2.0}), "missing")
    add("unknown param E", "moduli", lambda: solve(E=1.0), "unknown")
    add("params not a dict", "moduli", lambda: plate()[2].solve([1.0, 2.0]), "params", "dict")
    for nu in (0.5, 0.6, -1.0, NAN):
        add(f"moduli_from_young nu={nu}", "moduli", lambda nu=nu: bp.moduli_from_young(1.0, nu), "poisson")
    add("moduli_from_young E=-1", "moduli", lambda: bp.moduli_from_young(-1.0, 0.3), "young")
    for d in (NAN, INF, 0.0, -1.0, 0.5, 3.0):
        add(f"delta={d:g}", "horizon", lambda d=d: solve(delta=d), "delta", quick=d == 0.5)
    add("delta=1 (= h)", "horizon", lambda: finite_check(solve(delta=1.0)), "delta")
    add("delta=2.5 (= delta_max)", "horizon", lambda: finite_check(solve(delta=2.5)), "delta")
    for dm in (NAN, 0.0, -2.0, 0.5):
        add(f"find_bonds delta_max={dm:g}", "horizon", lambda dm=dm: bp.find_bonds(P(), dm), "delta_max", quick=dm == 0.0)
    add("find_bonds unknown rule", "horizon", lambda: bp.find_bonds(P(), 2.0, rule="cubic"), "rule")
    for h in (NAN, INF, 0.0, -1.0, 1e-200, 1e200):
        add(f"grid_2d h={h:g}", "particles", lambda h=h: bp.grid_2d(4.0, 2.0, h), "h", "spacing", "extent",
            quick=h == 0.0)
    add("grid_2d extent not a multiple of h", "particles", lambda: bp.grid_2d(4.5, 2.0, 1.0), "multiple of h")
    add("grid_2d negative length", "particles", lambda: bp.grid_2d(-4.0, 2.0, 1.0), "extent", "length", "multiple")
    for t in (0.0, -1.0, NAN):
        add(f"grid_2d thickness={t}", "particles", lambda t=t: bp.grid_2d(4.0, 2.0, 1.0, thickness=t), "thickness")
    add("grid_3d h=0", "particles", lambda: bp.grid_3d(2.0, 2.0, 2.0, 0.0), "h", "spacing")
    x = bp.grid_2d(6.0, 4.0, 1.0).x

    def pts(change, volume=None, shape=None):
        y = x.copy()
        change(y)
        return bp.from_points(y if shape is None else y.reshape(shape), np.ones(24) if volume is None else volume, h=1.0)
    add("particle at NaN", "particles", lambda: pts(lambda y: y.__setitem__((3, 0), NAN)), "nan", quick=True)
    add("particle at inf", "particles", lambda: pts(lambda y: y.__setitem__((3, 1), INF)), "nan", "inf")
    add("particle at 1e300", "particles", lambda: pts(lambda y: y.__setitem__((3, 1), 1e300)), "positions", "rescale")
    add("particles 1e-7 apart", "particles", lambda: pts(lambda y: y.__setitem__(3, y[2] + 1e-7)), "closer than", quick=True)
    add("duplicate particles", "particles", lambda: pts(lambda y: y.__setitem__(3, y[2])), "closer than")
    add("particles of 4 coordinates", "particles", lambda: bp.from_points(np.ones((6, 4)), np.ones(6)), "x must")
    add("particles empty", "particles", lambda: bp.from_points(np.zeros((0, 2)), np.zeros(0)), "x must", "non-empty")
    add("particles 1-D x", "particles", lambda: bp.from_points(np.arange(6.0), np.ones(6)), "x must")
    add("particle volume negative", "particles", lambda: pts(lambda y: None, np.r_[-1.0, np.ones(23)]), "volume")
    add("particle volume zero", "particles", lambda: pts(lambda y: None, np.r_[0.0, np.ones(23)]), "volume")
    add("particle volume NaN", "particles", lambda: pts(lambda y: None, np.r_[NAN, np.ones(23)]), "volume")
    add("particle volumes of wrong length", "particles", lambda: pts(lambda y: None, np.ones(5)), "volume")
    add("particles h=-1", "particles", lambda: bp.from_points(x, np.ones(24), h=-1.0), "h")
    add("layer of unknown side", "particles", lambda: P().layer("north", 1.0), "side")
    add("isolated particle", "particles", lambda: _isolated(), "empty family", "piece", "particle")
    add("eps=-1", "scene", lambda: scene_with(eps=-1.0), "eps")
    add("eps=NaN", "scene", lambda: scene_with(eps=NAN), "eps")
    add("eps=inf", "scene", lambda: scene_with(eps=INF), "eps")
    add("eps with pcg", "scene", lambda: scene_with(eps=1.0, solver="pcg"), "eps", "direct")
    add("solver unknown", "scene", lambda: scene_with(solver="cg"), "solver")
    add("noise not callable", "scene", lambda: scene_with(noise=3.0), "noise")
    add("pcg solve agrees with direct", "scene",
        lambda: (lambda u: finite_check(u, torch.allclose(u, unit_u(), rtol=1e-6, atol=1e-9)))(
            scene_with(solver="pcg").solve(PARAMS)), "solver")
    add("plane unknown", "scene", lambda: bp.LPS(P(), bp.find_bonds(P(), 2.5), plane="shell"), "plane")
    bonds = lambda: bp.find_bonds(P(), 2.5)
    add("precrack outside the body", "precrack", lambda: bp.precrack(P(), bonds(), [[50.0, 50.0], [60.0, 50.0]]),
        "pre-crack", quick=True)
    add("precrack of zero length", "precrack", lambda: bp.precrack(P(), bonds(), [[5.0, 3.0], [5.0, 3.0]]), "pre-crack")
    add("precrack with NaN end", "precrack", lambda: bp.precrack(P(), bonds(), [[5.0, NAN], [5.0, 3.0]]),
        "pre-crack", "crack", "nan")
    add("precrack of wrong shape", "precrack", lambda: bp.precrack(P(), bonds(), [1.0, 2.0, 3.0]), "pre-crack", "segment")
    add("precrack a string", "precrack", lambda: bp.precrack(P(), bonds(), "crack"), "pre-crack", "crack", "numbers")
    add("precrack cutting the body in two", "precrack", lambda: _cut_through(), "piece", "dirichlet")
    add("precrack inside: finite and softer", "precrack", lambda: _softer_with_crack(), "pre-crack")


def _isolated():
    p = bp.grid_2d(6.0, 4.0, 1.0)
    lonely = bp.from_points(np.vstack([p.x, [[20.0, 20.0]]]), np.append(p.volume, 1.0))
    mat = bp.BondBased(lonely, bp.find_bonds(lonely, 2.0))
    return bp.Scene(mat, [bp.Dirichlet.layer(lonely, "left", 2.0)], [bp.Load(lonely.x[:, 0] > 5, (1.0, 0.0))]).solve(
        {"K": 1.0, "delta": 2.0})


def _cut_through():
    p, _, scene = plate()
    b = bp.precrack(p, bp.find_bonds(p, 2.5), [[5.0, -1.0], [5.0, 7.0]])
    return bp.Scene(bp.LPS(p, b), scene.dirichlet, scene.loads)


def _softer_with_crack():
    p, _, scene = plate()
    b = bp.precrack(p, bp.find_bonds(p, 2.5), [[5.0, -1.0], [5.0, 3.0]])
    u = bp.Scene(bp.LPS(p, b), scene.dirichlet, scene.loads).solve(PARAMS)
    work, work0 = float((u * scene.force).sum()), float((unit_u() * scene.force).sum())
    return finite_check(u, work > work0, f"compliance {work:.4g} > uncracked {work0:.4g}: {work > work0}")


# --- observations ------------------------------------------------------------------------------

def observation_cases():
    P = lambda: plate()[0]
    add("observation of 0 points", "observe", lambda: bp.Observation(P(), np.zeros((0, 2))), "point", quick=True)
    add("observation outside the body", "observe", lambda: bp.Observation(P(), [[50.0, 3.0]]), "outside the body")
    add("observation at NaN", "observe", lambda: bp.Observation(P(), [[NAN, 3.0]]), "nan", "point")
    add("observation at inf", "observe", lambda: bp.Observation(P(), [[INF, 3.0]]), "inf", "point", "outside")
    add("observation of 3 coordinates in 2D", "observe", lambda: bp.Observation(P(), [[1.0, 2.0, 3.0]]), "point", "shape")
    add("observation a string", "observe", lambda: bp.Observation(P(), "abc"), "point", "numbers")
    add("observation interpolates affine u", "observe", lambda: _affine_observation(), "point")
    add("particle observation index past the end", "observe", lambda: bp.ParticleObservation(P(), [0, 999]),
        "particle", "index", "which")
    add("particle observation negative index", "observe", lambda: bp.ParticleObservation(P(), [-1]), "particle", "index", "which")
    add("particle observation empty", "observe", lambda: bp.ParticleObservation(P(), []), "particle", "which", "point")
    add("grid observation outside", "observe", lambda: bp.GridObservation(P(), [[50.0, 3.0]]), "outside")
    add("grid_points spacing 0", "observe", lambda: bp.grid_points((0.0, 0.0), (0.0, 1.0), (3, 3)), "spacing")
    add("grid_points origin NaN", "observe", lambda: bp.grid_points((NAN, 0.0), (1.0, 1.0), (3, 3)), "origin")
    add("grid_points counts 0", "observe", lambda: bp.grid_points((0.0, 0.0), (1.0, 1.0), (0, 3)), "count")
    add("edge_mask width -1", "observe", lambda: bp.edge_mask(P(), P().x[:3], -1.0), "width")
    add("edge_mask width NaN", "observe", lambda: bp.edge_mask(P(), P().x[:3], NAN), "width")
    add("opening observation component 5", "observe",
        lambda: bp.OpeningObservation(P(), P().x[:2] + 0.1, P().x[:2], component=5), "component")


def _affine_observation():
    p = plate()[0]
    pts = np.array([[3.3, 1.7], [7.1, 4.9]])
    A = torch.tensor([[1e-3, 2e-3], [-3e-3, 4e-3]])
    got = bp.Observation(p, pts)(torch.as_tensor(p.x) @ A.T)
    return finite_check(got, torch.allclose(got, torch.as_tensor(pts) @ A.T, rtol=1e-10, atol=1e-14))


# --- readers -----------------------------------------------------------------------------------

DICE_HEADER = "***\n*** DICe\n***\n"
DICE_ROW = "SUBSET_ID,COORDINATE_X,COORDINATE_Y,DISPLACEMENT_X,DISPLACEMENT_Y,SIGMA,STATUS_FLAG\n"


def dice_file(name, text: str | bytes):
    folder = TMP / f"dice-{name}"
    folder.mkdir(exist_ok=True)
    path = folder / "DICe_solution_1.txt"
    (path.write_bytes if isinstance(text, bytes) else path.write_text)(text)
    return path


def good_dice():
    rows = "".join(f"{k},{10.0 * k:.4E},{5.0:.4E},{0.1 * k:.4E},{-0.1 * k:.4E},0.01,4\n" for k in range(4))
    return DICE_HEADER + DICE_ROW + rows


def reader_cases():
    add("read_dice missing file", "readers", lambda: bp.read_dice([TMP / "nope" / "DICe_solution_1.txt"]),
        "nope", "DICe_solution", quick=True)
    add("read_dice empty file", "readers", lambda: bp.read_dice([dice_file("empty", "")]), "DICe_solution")
    add("read_dice binary", "readers", lambda: bp.read_dice([dice_file("binary", bytes(range(256)) * 8)]), "DICe_solution")
    add("read_dice garbage text", "readers", lambda: bp.read_dice([dice_file("garbage", "hello world\nfoo bar\n")]),
        "DICe_solution")
    add("read_dice header only", "readers", lambda: bp.read_dice([dice_file("header", DICE_HEADER + DICE_ROW)]),
        "DICe_solution")
    add("read_dice truncated mid-row", "readers",
        lambda: bp.read_dice([dice_file("truncated", good_dice()[:-12])]), "DICe_solution", quick=True)
    add("read_dice missing column", "readers",
        lambda: bp.read_dice([dice_file("nocolumn", good_dice().replace("DISPLACEMENT_Y", "DISP_Y"))]),
        "DISPLACEMENT_Y", "column")
    add("read_dice text in a number field", "readers",
        lambda: bp.read_dice([dice_file("text", good_dice().replace("0.01,4\n", "abc,4\n", 1))]), "DICe_solution")
    add("read_dice valid file", "readers", lambda: _dice_ok(), "DICe")
    add("read_dice a directory", "readers", lambda: bp.read_dice([TMP]), "DICe", str(TMP))
    add("frame_data scale NaN", "readers", lambda: bp.frame_data(bp.read_dice([dice_file("ok2", good_dice())]), 1, scale=NAN), "scale")
    add("frame_data missing frame", "readers", lambda: bp.frame_data(bp.read_dice([dice_file("ok3", good_dice())]), 7), "frame")
    for name, content in (("empty.msh", b""), ("binary.vtu", bytes(range(256)) * 4), ("garbage.msh", b"$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n3\n1 0 0\n"),
                          ("text.vtk", b"not a mesh at all\n"), ("plate.unknown", b"1 2 3\n")):
        add(f"from_mesh {name}", "readers", lambda name=name, content=content: _mesh(name, content), name,
            quick=name == "binary.vtu")
    add("from_mesh missing", "readers", lambda: bp.from_mesh(TMP / "none.msh"), "none.msh")
    from bayespd.infer import load
    for name, content in (("empty.nc", b""), ("garbage.nc", b"garbage" * 100), ("binary.nc", bytes(range(256)) * 16)):
        add(f"load {name}", "readers", lambda name=name, content=content: (_write(name, content), load(TMP / name)),
            name, quick=name == "garbage.nc")
    add("load missing .nc", "readers", lambda: load(TMP / "missing.nc"), "missing.nc")
    add("load truncated .nc", "readers", lambda: _truncated_tree(), "truncated.nc")
    add("load a directory", "readers", lambda: load(TMP), str(TMP))
    add("checkpoint chain file of garbage", "readers", lambda: _garbage_checkpoint(), "chain0.pt")
    add("ensemble store with a garbage plan", "readers", lambda: _garbage_plan(), "plan.json")


def _write(name, content):
    (TMP / name).write_bytes(content)


def _dice_ok():
    ds = bp.read_dice([dice_file("ok", good_dice())])
    u = np.asarray(ds["u"]) if "u" in ds else np.asarray(next(iter(ds.data_vars.values())))
    return bool(np.isfinite(u).any()) and ds.sizes.get("subset", 4) == 4, f"sizes {dict(ds.sizes)}"


def _mesh(name, content):
    _write(name, content)
    return bp.from_mesh(TMP / name)


def _truncated_tree():
    from bayespd.infer import load, save
    from bayespd.infer.datatree import build_tree
    tree = build_tree({"posterior": {"K": np.random.default_rng(0).normal(size=(2, 50))}})
    save(tree, TMP / "full.nc")
    data = (TMP / "full.nc").read_bytes()
    _write("truncated.nc", data[: len(data) // 2])
    return load(TMP / "truncated.nc")


def _garbage_checkpoint():
    from bayespd.infer import fit
    model, y = normal_model()
    folder = TMP / "garbage-ckpt"
    folder.mkdir(exist_ok=True)
    (folder / "chain0.pt").write_bytes(b"not a torch file" * 20)
    return fit(model, {"y": y}, "nuts", num_samples=5, num_warmup=5, num_chains=1, progress=False, checkpoint=folder)


def _garbage_plan():
    from bayespd.ensemble.store import EnsembleStore as Store
    folder = TMP / "garbage-store"
    folder.mkdir(exist_ok=True)
    (folder / "plan.json").write_text("{not json")
    return Store(folder, {"n": 3})


# --- fits: settings, data, priors ---------------------------------------------------------------

def normal_model(prior_scale=3.0):
    import pyro
    import pyro.distributions as dist

    y = 1.0 + torch.randn(10, generator=torch.Generator().manual_seed(0))

    def model(y):
        mu = pyro.sample("mu", dist.Normal(0.0, prior_scale))
        with pyro.plate("obs", 10):
            pyro.sample("y", dist.Normal(mu, 1.0), obs=y)
    return model, y


def fitted(method, check_mean=True, data=None, model=None, **kw):
    from bayespd.infer import fit
    m, y = normal_model()
    tree = fit(model or m, data or {"y": y}, method, progress=False, **kw)
    mu = tree["posterior"]["mu"].values
    # the exact posterior mean: y.sum() / (10 + 1/9)
    exact = float(y.sum()) / (10 + 1 / 9)
    ok = bool(np.isfinite(mu).all()) and (not check_mean or abs(mu.mean() - exact) < 0.5)
    return ok, f"posterior mean {mu.mean():.3f} (exact {exact:.3f})"


FAST = {"nuts": dict(num_samples=20, num_warmup=20, num_chains=1), "hmc": dict(num_samples=20, num_warmup=20, num_chains=1),
        "svi": dict(num_samples=50, svi_steps=400, svi_lr=0.05), "laplace": dict(num_samples=20)}


def fit_cases():
    from bayespd.infer import fit
    bad = {
        "nuts": [("num_samples", 0), ("num_samples", -5), ("num_samples", 2.5), ("num_samples", True), ("num_warmup", -1),
                 ("num_chains", 0), ("target_accept", 1.5), ("target_accept", 0.0), ("target_accept", 1.0),
                 ("target_accept", NAN), ("max_tree_depth", 0), ("checkpoint_every", 0), ("chains", "threads"),
                 ("seed", -1), ("init", "random"), ("map_starts", 0), ("modes", "all"), ("step_size", 0.1)],
        "hmc": [("trajectory_length", -1.0), ("trajectory_length", 0.0), ("trajectory_length", NAN),
                ("trajectory_length", INF), ("num_warmup", "10"), ("target_accept", -0.1)],
        "svi": [("svi_steps", 0), ("svi_steps", -3), ("svi_lr", 0.0), ("svi_lr", -0.1), ("svi_lr", NAN),
                ("svi_lr", INF), ("svi_particles", 0), ("svi_rank", 0), ("guide", "gaussian"), ("num_samples", 0)],
        "laplace": [("hessian", "bfgs"), ("num_samples", -1), ("map_starts", 0), ("init_values", {"mu": NAN})],
    }
    for method, rows in bad.items():
        for key, value in rows:
            add(f"{method} {key}={value!r}", "fit settings",
                lambda method=method, key=key, value=value: fitted(method, **dict(FAST[method], **{key: value})),
                key.split("_")[0] if key == "init_values" else key, "mu" if key == "init_values" else key,
                quick=(method, key) in (("nuts", "target_accept"), ("svi", "svi_steps")))
    add("svi svi_lr=1e6 (divergence)", "fit settings", lambda: fitted("svi", **dict(FAST["svi"], svi_lr=1e6)), "svi_lr")
    add("svi svi_lr=1e-12 (no move, finite)", "fit settings",
        lambda: fitted("svi", check_mean=False, **dict(FAST["svi"], svi_lr=1e-12)), "svi_lr")
    add("method unknown", "fit settings", lambda: fitted("mcmc"), "method")
    add("method an int", "fit settings", lambda: fitted(3), "method")
    add("setting of another method", "fit settings", lambda: fitted("svi", max_tree_depth=3), "max_tree_depth")
    for method in FAST:
        add(f"{method} runs (posterior mean)", "fit settings", lambda method=method: fitted(method, **FAST[method]),
            method, timeout=120, quick=method == "laplace")
    add("nuts 1 draw, 0 warmup", "fit settings",
        lambda: fitted("nuts", check_mean=False, num_samples=1, num_warmup=0, num_chains=1), "num", timeout=120)
    _, y = normal_model()
    for label, data in (("y as numpy", {"y": y.numpy()}), ("y as a list", {"y": y.tolist()}),
                        ("y float32", {"y": y.float()}), ("y int", {"y": y.round().long()})):
        add(f"data {label}", "data", lambda data=data: fitted("laplace", data=data, **FAST["laplace"]), "y")
    for label, data in (("y with NaN", {"y": y.index_fill(0, torch.tensor([2]), NAN)}),
                        ("y with inf", {"y": y.index_fill(0, torch.tensor([2]), INF)}),
                        ("y with 1e300", {"y": y.index_fill(0, torch.tensor([2]), 1e300)}),
                        ("y of wrong shape", {"y": y[:7]}), ("y 2-D", {"y": y[None]}), ("y a string", {"y": "data"}),
                        ("y strings in numpy", {"y": np.array(["a"] * 10)}), ("no y", {"x": y}), ("data not a dict", [y]),
                        ("y ragged list", {"y": [[1.0], [1.0, 2.0]]}), ("extra key", {"y": y, "z": y})):
        add(f"data {label}", "data", lambda data=data: fitted("laplace", data=data, **FAST["laplace"]), "y", "data",
            "z", quick=label == "y with NaN")
    import pyro
    import pyro.distributions as dist

    def prior_model(prior):
        def model(y):
            mu = pyro.sample("mu", prior)
            with pyro.plate("obs", 10):
                pyro.sample("y", dist.Normal(mu if mu.dim() == 0 else mu.float().double(), 1.0), obs=y)
        return model
    add("prior discrete (Poisson)", "priors", lambda: fitted("laplace", model=prior_model(dist.Poisson(3.0)), **FAST["laplace"]),
        "mu", "discrete", quick=True)
    add("prior Normal(nan, 1)", "priors", lambda: fitted("laplace", model=prior_model(dist.Normal(torch.tensor(NAN), 1.0, validate_args=False)), **FAST["laplace"]),
        "mu")
    add("prior point mass (Delta)", "priors", lambda: fitted("laplace", model=prior_model(dist.Delta(torch.tensor(1.0))), **FAST["laplace"]),
        "mu")
    add("prior Normal on K leaves K > 0 (scene)", "priors", lambda: _plate_prior_case(), "K", timeout=120)
    add("prior far from data (finite)", "priors",
        lambda: fitted("laplace", check_mean=False, model=prior_model(dist.Normal(1e3, 1.0)), **FAST["laplace"]), "mu")


def _plate_prior_case():
    import pyro.distributions as dist
    from bayespd.infer import fit
    from bayespd.models.elastic_plate import elastic_plate
    scene = plate()[2]
    model = elastic_plate(scene, {"K": 1000.0, "G": 600.0}, 1e-3, priors={"K": dist.Normal(1000.0, 500.0)})
    y = scene.predict(PARAMS)
    return fitted("laplace", model=model, data={"y": y}, scene=scene, num_samples=10)


# --- CLI --------------------------------------------------------------------------------------

TINY_MODEL = '''
import math, os, time
import pyro, pyro.distributions as dist, torch
import bayespd as bp

PAUSE = float(os.environ.get("TINY_PAUSE", "0"))
SCALE = float(os.environ.get("TINY_PRIOR_SCALE", "0.5"))


def scene():
    p = bp.grid_2d(6.0, 3.0, 1.0)
    return bp.Scene(bp.BondBased(p, bp.find_bonds(p, 2.0)), [bp.Dirichlet.layer(p, "left", 2.0)],
                    [bp.Load(p.layer("right", 1.0), (10.0, 0.0))], bp.Observation(p, p.x[p.x[:, 0] > 2.0]))


def model(scene):
    def m(y=None):
        if PAUSE and torch.is_grad_enabled():
            time.sleep(PAUSE)
        K = pyro.sample("K", dist.LogNormal(math.log(2500.0), SCALE))
        mean = scene.observe(scene.solve({"K": K, "delta": 2.0}))
        with pyro.plate("point", mean.shape[0], dim=-2), pyro.plate("component", 2, dim=-1):
            pyro.sample("y", dist.Normal(mean, 1e-3), obs=y)
    return m
'''


@cache
def tiny():
    folder = TMP / "tiny"
    folder.mkdir(exist_ok=True)
    (folder / "model.py").write_text(TINY_MODEL)
    space = {}
    exec(TINY_MODEL, space)
    scene = space["scene"]()
    u = scene.observe(scene.solve({"K": torch.tensor(3000.0), "delta": 2.0}))
    y = (u + 1e-3 * torch.randn(u.shape, generator=torch.Generator().manual_seed(0))).numpy()
    np.savez(folder / "data.npz", y=y)
    return folder


def cli(*args, env=None, timeout=240):
    return subprocess.run([sys.executable, "-m", "bayespd.cli", *map(str, args)], capture_output=True, text=True,
                          env=env or ENV, timeout=timeout, cwd=TMP)


class CLIResult(Exception):
    """A CLI run's outcome, carried out of a case (classified by ``cli_outcome``)."""


def cli_case(*args, check=None):
    def run():
        r = cli(*[a() if callable(a) else a for a in args])
        return ("cli", r.returncode, r.stderr, check(r) if (check and r.returncode == 0) else (r.returncode == 0, "exit 0"))
    return run


def calibrate(*extra, method="svi", model=None, data=None):
    given = lambda v, default: (v() if callable(v) else v) if v is not None else default()
    return ("calibrate", lambda: given(model, lambda: tiny() / "model.py"), "--data",
            lambda: given(data, lambda: tiny() / "data.npz"),
            "--method", method, "--out", lambda: TMP / "cli-out", "--quiet", *extra)


def bad_file(name, content):
    def make():
        path = TMP / name
        (path.write_bytes if isinstance(content, bytes) else path.write_text)(content)
        return path
    return make


def cli_cases():
    add("cli no arguments", "cli", cli_case(), "usage", quick=True)
    add("cli unknown command", "cli", cli_case("fly"), "invalid choice", "fly")
    add("cli calibrate method mcmc", "cli", cli_case(*calibrate(method="mcmc")), "mcmc")
    add("cli model missing", "cli", cli_case(*calibrate(model=TMP / "nope.py")), "nope.py")
    add("cli data missing", "cli", cli_case(*calibrate(data=TMP / "nope.npz")), "nope.npz")
    add("cli model syntax error", "cli", cli_case(*calibrate(model=bad_file("syntax.py", "def scene(:\n"))), "syntax.py",
        quick=True)
    add("cli model wrong signature", "cli", cli_case(*calibrate(model=bad_file("sig.py", "def scene(n):\n    pass\n"
                                                                            "def model(s):\n    pass\n"))), "sig.py")
    add("cli model without model()", "cli", cli_case(*calibrate(model=bad_file("nomodel.py", "def scene():\n    pass\n"))),
        "nomodel.py", "model(scene)")
    add("cli model raising on import", "cli", cli_case(*calibrate(model=bad_file("raises.py", "raise RuntimeError('boom')\n"))),
        "raises.py")
    add("cli data truncated npz", "cli", cli_case(*calibrate(data=lambda: _truncated_npz())), "truncated.npz")
    add("cli data not a zip", "cli", cli_case(*calibrate(data=bad_file("text.npz", "hello"))), "text.npz")
    add("cli data binary garbage", "cli", cli_case(*calibrate(data=bad_file("binary.npz", bytes(range(256)) * 4))), "binary.npz")
    add("cli data string array", "cli", cli_case(*calibrate(data=lambda: _npz("strings.npz", y=np.array(["a", "b"])))), "strings.npz")
    add("cli data extra key", "cli", cli_case(*calibrate(data=lambda: _npz("extra.npz", y=np.zeros((12, 2)), z=np.ones(3)))),
        "extra.npz", "'z'")
    add("cli data no y", "cli", cli_case(*calibrate(data=lambda: _npz("noy.npz", u=np.zeros(3)))), "'y'")
    add("cli data of wrong shape", "cli", cli_case(*calibrate(data=lambda: _npz("shape.npz", y=np.zeros((5, 2))))), "y")
    add("cli data with NaN", "cli", cli_case(*calibrate(data=lambda: _npz("nan.npz", y=np.full((12, 2), NAN)))), "y")
    for flag, value in (("--warmup", "-1"), ("--samples", "0"), ("--chains", "0"), ("--checkpoint-every", "0"),
                        ("--svi-steps", "x"), ("--seed", "one"), ("--samples", "1e3")):
        add(f"cli {flag} {value}", "cli", cli_case(*calibrate(flag, value, method="nuts")), flag)
    add("cli checkpoint with svi", "cli", cli_case(*calibrate("--checkpoint", TMP / "ck-svi")), "--checkpoint")
    add("cli summary of an empty dir", "cli", cli_case("summary", TMP / "empty-dir-made"), "posterior.nc", "empty-dir")
    add("cli summary of garbage posterior", "cli", cli_case("summary", lambda: _garbage_dir()), "posterior.nc")
    add("cli predict without scene file", "cli", cli_case("predict", lambda: _laplace_dir(), "--scene", TMP / "noscene.py"),
        "noscene.py", timeout=240)
    add("cli predict without posterior", "cli", cli_case("predict", TMP / "nothing", "--scene", TMP / "noscene.py"), "nothing")
    add("cli predict bad device", "cli", cli_case("predict", lambda: _laplace_dir(), "--scene", lambda: _scene_file(), "--n", "2",
                                                  "--device", "gpu"), "device", timeout=240)
    add("cli predict n=0", "cli", cli_case("predict", lambda: _laplace_dir(), "--scene", lambda: _scene_file(), "--n", "0"),
        "n", timeout=240)
    add("cli laplace runs", "cli", cli_case(*calibrate("--samples", "50", method="laplace"), check=_cli_posterior),
        "laplace", timeout=240)


def _npz(name, **arrays):
    np.savez(TMP / name, **arrays)
    return TMP / name


def _truncated_npz():
    data = (tiny() / "data.npz").read_bytes()
    (TMP / "truncated.npz").write_bytes(data[: len(data) // 2])
    return TMP / "truncated.npz"


def _garbage_dir():
    folder = TMP / "garbage-dir"
    folder.mkdir(exist_ok=True)
    (folder / "posterior.nc").write_bytes(b"garbage" * 50)
    return folder


def _cli_posterior(r):
    """The CLI's Laplace posterior is the API's (same model, data and seed), finite; with noise as
    large as the signal (sigma 1e-3) the truth K = 3000 lies inside its 99.9 % interval."""
    from bayespd.infer import fit, load
    K = load(TMP / "cli-out" / "posterior.nc")["posterior"]["K"].values
    space = {}
    exec(TINY_MODEL, space)
    y = torch.as_tensor(np.load(tiny() / "data.npz")["y"])
    api = fit(space["model"](space["scene"]()), {"y": y}, "laplace", num_samples=50, progress=False)["posterior"]["K"].values
    lo, hi = np.quantile(K, [0.0005, 0.9995])
    ok = bool(np.isfinite(K).all()) and abs(np.median(K) / np.median(api) - 1) < 1e-6 and lo < 3000 < hi
    return ok, f"median K {np.median(K):.0f} (API {np.median(api):.0f}), 99.9% interval [{lo:.0f}, {hi:.0f}] holds 3000"


def _laplace_dir():
    folder = TMP / "laplace-dir"
    if not (folder / "posterior.nc").exists():
        r = cli("calibrate", tiny() / "model.py", "--data", tiny() / "data.npz", "--method", "laplace", "--out", folder,
                "--quiet", "--samples", "20")
        assert r.returncode == 0, r.stderr
    return folder


def _scene_file():
    path = TMP / "scene.py"
    path.write_text("from bayespd.scenes.notched_plate import notched_plate\n\n\ndef fracture_scene():\n"
                    "    return notched_plate(side=16.0, h=1.0, steps=10, sigma=100.0)\n")
    return path


# --- stability extremes (experiments/stability.py) -------------------------------------------------

def stability_cases():
    import stability as st

    def patch(cls, m, params, plane="stress", interior=6):
        r = st.patch_test(cls, m, params, plane, interior=interior)
        return r["error"] <= r["bound"], f"error {r['error']:.2e} <= bound {r['bound']:.2e}"
    for nu in (0.49, 0.4999):
        K, G = (float(v) for v in bp.moduli_from_young(1.0, nu))
        add(f"stability nu={nu} plane strain patch test", "stability",
            lambda K=K, G=G: patch(bp.LPS, 3, {"K": K, "G": G}, "strain"), "nu", quick=nu == 0.4999)
    add("stability nu=0.5 refused", "stability", lambda: bp.moduli_from_young(1.0, 0.5), "poisson")
    for contrast in (1e6, 1e8):
        def run(contrast=contrast):
            r = st.contrast_case(contrast, bp.LPS, length=20.0, width=3.0, delta=2.0)
            if "refused" in r:  # the suite caught the library's refusal (a message naming the fix)
                return True, f"refused inside the stability suite: {r['refused'][:160]}"
            return r["stable"] and r["error"] <= r["bound"], f"error {r['error']:.2e} <= bound {r['bound']:.2e}"
        add(f"stability contrast {contrast:g}", "stability", run, "contrast", timeout=120)
    for m in (1.5, 10):
        add(f"stability delta/h={m} patch test", "stability", lambda m=m: patch(bp.BondBased, m, {"K": 1.0}), "delta",
            timeout=120)
    add("stability isolated particle eps=0 refused", "stability", lambda: _isolated_eps0(), "eps > 0", "particle")
    add("stability isolated particle eps>0 handled", "stability", lambda: _isolated_eps(), "eps")
    add("stability float32 explicit dynamics", "stability", lambda: _precision(st), "float32", timeout=180)
    add("stability explicit dt above the limit refused", "stability", lambda: _explicit_unstable(), "dt", "time step")
    add("stability langevin at 100x the explicit limit", "stability", lambda: _langevin(st), "dt", timeout=300)


def _isolated_eps0():
    import stability as st
    mat, params, c, load, intact, k = st.isolated_body()
    return bp.solvers.linear_elastic(mat, params, load, eps=0.0, constraints=c, intact=intact).equilibrium()


def _isolated_eps():
    import stability as st
    rows = st.isolated(quick=True)["rows"]
    ok = all(r["stable"] and r["isolated_displacement"] == 0.0 and r["error"] <= r["eps_over_lambda_min"] for r in rows)
    return ok, f"{len(rows)} eps values, error <= eps / lambda_min: {ok}"


def _precision(st):
    e = st.precision(quick=True)
    ok = e["dtype_kept"] == "torch.float32" and e["displacement_rel_diff_max"] < e["bound_n_eps32"]
    return ok, f"float32 drift {e['displacement_rel_diff_max']:.2e} < n eps32 {e['bound_n_eps32']:.2e}"


def _explicit_unstable():
    from bayespd.solvers import critical_time_step, lumped_mass, velocity_verlet
    p = bp.grid_2d(6.0, 3.0, 1.0)
    mat = bp.BondBased(p, bp.find_bonds(p, 2.0))
    params = {"K": 1.0, "delta": 2.0}
    K = mat.pattern.matrix(mat.numeric_stiffness(params)).tocsr()
    mass = lumped_mass(p, 1.0)
    dt = 10 * critical_time_step(K, mass)
    force = lambda u: -torch.as_tensor(K @ u.detach().numpy())
    return velocity_verlet(force, mass, 1e-3 * torch.ones(2 * p.n), dt, 50, stiffness=K)


def _langevin(st):
    f = st.langevin(quick=True)
    half = f["theta_0.5"]
    ok = "reduce dt below" in f["euler_maruyama_refused"] and half["stable"] and half["max_abs_z_vs_eta_Ainv"] < 4.5
    return ok, (f"Euler-Maruyama refused inside the suite naming dt and the fix: {'reduce dt below' in f['euler_maruyama_refused']}; "
                f"theta = 1/2 samples eta A^-1 (z-max {half['max_abs_z_vs_eta_Ainv']:.2f})")


# --- kill / resume ------------------------------------------------------------------------------

CHAIN_SCRIPT = '''
import multiprocessing, os, sys, time
from pathlib import Path
import numpy as np, pyro, pyro.distributions as dist, torch
from bayespd.infer import fit

torch.set_default_dtype(torch.float64)
torch.set_num_threads(1)
Y = 1.0 + torch.randn(20, generator=torch.Generator().manual_seed(0))


class Slow:
    def __init__(self, folder, pause):
        self.folder, self.pause = Path(folder), pause

    def __call__(self, y):
        if torch.is_grad_enabled() and self.pause:
            mark = self.folder / (multiprocessing.current_process().name + ".pid")
            if not mark.exists():
                mark.write_text(str(os.getpid()))
            time.sleep(self.pause)
        mu = pyro.sample("mu", dist.Normal(0.0, 3.0))
        with pyro.plate("obs", 20):
            pyro.sample("y", dist.Normal(mu, 1.0), obs=y)


RUN = dict(num_warmup=30, num_samples=40, num_chains=2, seed=5, progress=False, checkpoint_every=5)

if __name__ == "__main__":
    folder, pause, chains = sys.argv[1], float(sys.argv[2]), sys.argv[3]
    ck = None if chains == "sequential" else Path(folder) / "ckpt"
    tree = fit(Slow(folder, pause), {"y": Y}, chains=chains, checkpoint=ck, **RUN)
    np.save(Path(folder) / f"mu-{chains}.npy", tree["posterior"]["mu"].values)
'''


def wait_for(condition, timeout=120):
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            raise TimeoutError("the run never reached the point to kill it")
        time.sleep(0.05)


def nuts_api_kill_resume():
    folder = TMP / "kill-api"
    folder.mkdir(exist_ok=True)
    script = folder / "script.py"
    script.write_text(CHAIN_SCRIPT)
    go = lambda pause, chains: subprocess.Popen([sys.executable, str(script), str(folder), str(pause), chains], cwd=folder,
                                                env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ref = go(0.0, "sequential")
    ref.communicate(timeout=180)
    run = go(0.01, "processes")
    wait_for(lambda: all((folder / f"chain {c}.pid").exists() for c in (0, 1)))
    pid = int((folder / "chain 1.pid").read_text())
    wait_for(lambda: (folder / "ckpt" / "chain1.pt").exists())
    os.kill(pid, signal.SIGKILL)
    _, err = run.communicate(timeout=120)
    named = run.returncode == 1 and "WorkerError" in err and "chain 1" in err
    again = go(0.0, "processes")
    _, err2 = again.communicate(timeout=180)
    same = again.returncode == 0 and np.array_equal(np.load(folder / "mu-processes.npy"), np.load(folder / "mu-sequential.npy"))
    return named and same, f"killed worker named (WorkerError, chain 1): {named}; resumed bit-identical: {same}"


def cli_kill_resume():
    folder = tiny()
    args = ["calibrate", folder / "model.py", "--data", folder / "data.npz", "--method", "nuts", "--warmup", "30",
            "--chains", "1", "--seed", "3", "--quiet", "--samples", "60"]
    whole = cli(*args, "--out", TMP / "cli-whole")
    assert whole.returncode == 0, whole.stderr
    ck = TMP / "cli-ck"
    command = [sys.executable, "-m", "bayespd.cli", *map(str, args), "--out", str(TMP / "cli-resumed"), "--checkpoint",
               str(ck), "--checkpoint-every", "5"]
    run = subprocess.Popen(command, env=dict(ENV, TINY_PAUSE="0.02"), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                           cwd=TMP)
    saved = ck / "chain0.pt"

    def enough():
        try:
            return saved.exists() and len(torch.load(saved, weights_only=True)["draws"].get("K", [])) >= 10
        except Exception:
            return False
    wait_for(enough)
    run.kill()
    run.wait(10)
    part = len(torch.load(saved, weights_only=True)["draws"]["K"])
    done = subprocess.run(command, env=ENV, capture_output=True, text=True, timeout=180, cwd=TMP)
    from bayespd.infer import load
    a, b = load(TMP / "cli-whole" / "posterior.nc"), load(TMP / "cli-resumed" / "posterior.nc")
    same = done.returncode == 0 and all(a[g].to_dataset().identical(b[g].to_dataset()) for g in ("posterior", "sample_stats"))
    return same and part < 60, f"killed at {part} of 60 draws; resumed bit-identical: {same}"


def checkpoint_refuses(change):
    from bayespd.infer import fit
    folder = TMP / f"ck-{change}"
    model, y = normal_model()
    run = dict(num_samples=5, num_warmup=10, num_chains=1, progress=False, checkpoint=folder)
    fit(model, {"y": y}, "nuts", **run)
    if change == "data":
        return fit(model, {"y": y + 1e-12}, "nuts", **run)
    return fit(normal_model(prior_scale=2.0)[0], {"y": y}, "nuts", **run)


ENSEMBLE_SCRIPT = '''
import sys
import numpy as np, torch
torch.set_num_threads(1)
from bayespd.ensemble import predictive
from bayespd.infer.datatree import build_tree
from bayespd.scenes.notched_plate import notched_plate

predictive.BATCH = 1
import bayespd.ensemble.scene as es
es.BATCH = 1
rng = np.random.default_rng(0)
tree = build_tree({"posterior": {"K": 3000.0 * (1 + 0.05 * rng.standard_normal((2, 10))),
                                 "s0": 0.0094 * (1 + 0.05 * rng.standard_normal((2, 10)))}})
if __name__ == "__main__":
    scene = notched_plate(side=16.0, h=1.0, steps=20, sigma=100.0)
    ds = predictive.ensemble(tree, scene, 4, n_mean=2, store=sys.argv[1], workers=1, progress=False)
'''


def ensemble_kill_resume():
    import xarray as xr
    folder = TMP / "ensemble"
    folder.mkdir(exist_ok=True)
    script = folder / "script.py"
    script.write_text(ENSEMBLE_SCRIPT)
    go = lambda store: subprocess.Popen([sys.executable, str(script), str(store)], cwd=folder, env=ENV,
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    whole = go(folder / "whole")
    _, err = whole.communicate(timeout=400)
    assert whole.returncode == 0, err
    killed = go(folder / "resumed")
    wait_for(lambda: len(list((folder / "resumed").glob("*-0*.npz"))) >= 2, timeout=300)
    killed.kill()
    killed.wait(10)
    before = len(list((folder / "resumed").glob("*-0*.npz")))
    again = go(folder / "resumed")
    _, err = again.communicate(timeout=400)
    assert again.returncode == 0, err
    files = sorted(p.name for p in (folder / "whole").glob("*.npz"))
    def same_arrays(f):  # every array bit for bit but the run's own timings
        with np.load(folder / "whole" / f) as a, np.load(folder / "resumed" / f) as b:
            return a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files if not k.endswith("time_s"))
    same_files = all(same_arrays(f) for f in files)
    with xr.open_dataset(folder / "whole" / "ensemble.nc") as a, xr.open_dataset(folder / "resumed" / "ensemble.nc") as b:
        keep = [v for v in a.data_vars if "time" not in v]
        same = a[keep].load().identical(b[keep].load())
    return same and same_files and before < 6, (f"killed with {before} of 6 realisations written; resumed "
                                                  f"realisations bit-identical (timings aside): {same_files}; aggregate identical: {same}")


def kill_cases():
    add("kill/resume NUTS API (SIGKILLed worker)", "kill/resume", nuts_api_kill_resume, "chain", timeout=500, quick=True)
    add("kill/resume CLI (SIGKILL)", "kill/resume", cli_kill_resume, "checkpoint", timeout=500)
    add("checkpoint refuses changed data", "kill/resume", lambda: checkpoint_refuses("data"), "ck-data", quick=True)
    add("checkpoint refuses a changed prior", "kill/resume", lambda: checkpoint_refuses("prior"), "ck-prior")
    add("kill/resume crack ensemble (SIGKILL)", "kill/resume", ensemble_kill_resume, "store", timeout=580)
    from bayespd.ensemble.predictive import ensemble
    from bayespd.infer.datatree import build_tree
    tree = lambda: build_tree({"posterior": {"K": np.full((1, 4), 3000.0), "s0": np.full((1, 4), 0.0094)}})
    scene = cache(lambda: __import__("bayespd.scenes.notched_plate", fromlist=["x"]).notched_plate(side=16.0, h=1.0, steps=10))
    add("ensemble device 'gpu'", "ensemble", lambda: ensemble(tree(), scene(), 2, store=TMP / "e1", device="gpu"), "device")
    add("ensemble device 'cuda:7'", "ensemble", lambda: ensemble(tree(), scene(), 2, store=TMP / "e2", device="cuda:7"), "device")
    add("ensemble n=0", "ensemble", lambda: ensemble(tree(), scene(), 0, store=TMP / "e3", workers=1), "n")
    add("ensemble n=-3", "ensemble", lambda: ensemble(tree(), scene(), -3, store=TMP / "e4", workers=1), "n")
    add("ensemble workers=0", "ensemble", lambda: ensemble(tree(), scene(), 2, store=TMP / "e5", workers=0), "workers")
    add("ensemble posterior without s0", "ensemble",
        lambda: ensemble(build_tree({"posterior": {"K": np.full((1, 4), 3000.0)}}), scene(), 2, store=TMP / "e6", workers=1),
        "s0")
    add("ensemble store is a file", "ensemble", lambda: (_write("store-file", b"x"), ensemble(tree(), scene(), 2, store=TMP / "store-file", workers=1)),
        "store-file", "store")


# --- runner ---------------------------------------------------------------------------------------

def classify_error(error: BaseException, names) -> tuple[str, str]:
    frames = traceback.extract_tb(error.__traceback__)
    inner = Path(frames[-1].filename).resolve() if frames else Path("?")
    ours = inner.is_relative_to(PACKAGE)
    kind = isinstance(error, (ValueError, TypeError, FileNotFoundError)) or type(error).__module__.startswith("bayespd")
    message = str(error).replace("\n", " ")
    detail = f"{type(error).__name__}: {message[:220]}"
    if not (ours and kind):
        return "raw_exception", detail + f" [raised in {inner.parent.name}/{inner.name}:{frames[-1].lineno if frames else '?'}]"
    if names and not any(n.lower() in message.lower() for n in names):
        return "raw_exception", detail + f" [names none of {list(names)}]"
    return "refused", detail


def run_case(c) -> tuple[str, str]:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = c["fn"]()
    except Exception as error:  # noqa: BLE001 -- the point is to classify every exception
        return classify_error(error, c["names"])
    if isinstance(result, tuple) and len(result) == 4 and result[0] == "cli":
        _, code, err, (ok, detail) = result
        if code == 0:
            return ("handled" if ok else "silent_wrong"), detail
        last = err.strip().splitlines()[-1] if err.strip() else ""
        if "Traceback" in err:
            return "raw_exception", f"exit {code} with a traceback: {last[:220]}"
        if not any(n.lower() in err.lower() for n in c["names"]):
            return "raw_exception", f"exit {code}, names none of {list(c['names'])}: {last[:220]}"
        return "refused", f"exit {code}: {last[:220]}"
    if isinstance(result, tuple) and len(result) == 2 and isinstance(result[0], (bool, np.bool_)):
        return ("handled" if result[0] else "silent_wrong"), str(result[1])
    return "silent_wrong", f"accepted without a check: returned {type(result).__name__}"


def worker(conn):
    torch.set_num_threads(1)
    while True:
        i = conn.recv()
        if i is None:
            return
        t0 = time.perf_counter()
        outcome, detail = run_case(CASES[i])
        conn.send((outcome, detail, time.perf_counter() - t0))


class Pool:
    """One forked worker that runs cases in turn; a case past its limit kills it (a hang)."""

    def __init__(self):
        self.proc = None

    def start(self):
        self.conn, child = mp.get_context("fork").Pipe()
        self.proc = mp.get_context("fork").Process(target=worker, args=(child,), daemon=True)
        self.proc.start()

    def run(self, i):
        if self.proc is None or not self.proc.is_alive():
            self.start()
        t0 = time.perf_counter()
        self.conn.send(i)
        if self.conn.poll(CASES[i]["timeout"]):
            try:
                return self.conn.recv()
            except EOFError:
                pass
            self.proc = None
            return "raw_exception", "the worker process died (a crash inside a dependency)", time.perf_counter() - t0
        self.proc.kill()
        self.proc.join(5)
        self.proc = None
        return "hang", f"no answer within {CASES[i]['timeout']} s", time.perf_counter() - t0


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a subset of the cases, < 2 minutes")
    parser.add_argument("--only", default=None, help="run only the cases whose name contains this")
    args = parser.parse_args()
    for build in (scene_cases, observation_cases, reader_cases, fit_cases, cli_cases, stability_cases, kill_cases):
        build()
    chosen = [i for i, c in enumerate(CASES) if (c["quick"] or not args.quick) and (args.only is None or args.only in c["name"])]
    plate(), unit_u(), tiny()  # built before the fork, shared by every case
    t0 = time.perf_counter()
    pool, rows = Pool(), []
    for i in chosen:
        outcome, detail, seconds = pool.run(i)
        c = CASES[i]
        rows.append(dict(name=c["name"], group=c["group"], outcome=outcome, detail=detail, seconds=round(seconds, 2)))
        print(f"{outcome:13s} {seconds:6.1f}s  [{c['group']}] {c['name']}: {detail}", flush=True)
    if pool.proc is not None:
        pool.conn.send(None)
        pool.proc.join(5)
    counts = {o: sum(r["outcome"] == o for r in rows) for o in OUTCOMES}
    wall = time.perf_counter() - t0
    print("counts: " + ", ".join(f"{k} {v}" for k, v in counts.items()) + f" ({len(rows)} cases, {wall:.0f} s)")
    kill = {r["name"]: r["outcome"] for r in rows if r["group"] == "kill/resume"}
    resumes = [k for k in kill if k.startswith("kill/resume")]
    refusals = [k for k in kill if k.startswith("checkpoint refuses")]
    targets = {
        "silent_wrong": {"value": counts["silent_wrong"], "target": 0, "passed": counts["silent_wrong"] == 0},
        "hang": {"value": counts["hang"], "target": 0, "passed": counts["hang"] == 0},
        "raw_exception": {"value": counts["raw_exception"], "target": 0, "passed": counts["raw_exception"] == 0},
        "kill_resume_bit_identical": {"value": {k: kill[k] for k in resumes}, "target": "handled (bit-identical)",
                                      "passed": bool(resumes) and all(kill[k] == "handled" for k in resumes)},
        "checkpoint_refuses_changed_run": {"value": {k: kill[k] for k in refusals}, "target": "refused",
                                           "passed": bool(refusals) and all(kill[k] == "refused" for k in refusals)},
    }
    if not args.quick:
        targets["cases_at_least_150"] = {"value": len(rows), "target": 150, "passed": len(rows) >= 150}
    write_metrics("reliability", {
        "wall_time_s": wall, "settings": {"quick": args.quick, "only": args.only, "cases": len(rows),
                                          "classification": "see the module docstring"},
        "counts": counts, "by_group": {g: {o: sum(r["outcome"] == o for r in rows if r["group"] == g) for o in OUTCOMES}
                                       for g in dict.fromkeys(r["group"] for r in rows)},
        "targets": targets, "cases": rows})


if __name__ == "__main__":
    main()
