"""Inputs of ``bayespd demo``: a MODEL.py, a SCENE.py and a DATA.npz written to a folder, so
the demo runs the command line on exactly the files a user would write (copy them).

The model calibrates the bulk modulus K of a bond-based plate (delta = 3 mm) from noisy
displacements made on a grid twice as fine (no inverse crime); the critical stretch s0 has a
prior only (elastic data do not inform it), so the crack ensemble's epistemic part comes from
K's posterior and s0's prior.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch

from bayespd.atomic import atomic_path

MODEL_PY = '''"""MODEL.py for `bayespd calibrate`: scene(), model(scene), and for tikhonov init() (+ fixed())."""
import math

import pyro
import pyro.distributions as dist

import bayespd as bp

L, W, DELTA, FORCE = 20.0, 10.0, 3.0, (100.0, 0.0)  # mm, mm, mm, N


def scene(h=1.0, points=None):
    """Bond-based plate clamped on the left, pulled on the right; observed at the particles
    of the h = 1 grid right of the clamp (or at ``points``)."""
    p = bp.grid_2d(L, W, h)
    if points is None:
        points = p.x[p.x[:, 0] > DELTA]
    return bp.Scene(bp.BondBased(p, bp.find_bonds(p, DELTA)), [bp.Dirichlet.layer(p, "left", DELTA)],
                    [bp.Load(p.layer("right", h), FORCE)], bp.Observation(p, points))


def model(scene):
    """K ~ LogNormal(log 2500, 0.5); s0 ~ LogNormal(log 0.0094, 0.1) (prior only);
    sigma ~ HalfNormal(1e-3); y ~ Normal(H u(K), sigma)."""
    def m(y=None):
        K = pyro.sample("K", dist.LogNormal(math.log(2500.0), 0.5))
        pyro.sample("s0", dist.LogNormal(math.log(0.0094), 0.1))
        sigma = pyro.sample("sigma", dist.HalfNormal(1e-3))
        mean = scene.observe(scene.solve({"K": K, "delta": DELTA}))
        with pyro.plate("point", mean.shape[0], dim=-2), pyro.plate("component", mean.shape[1], dim=-1):
            pyro.sample("y", dist.Normal(mean, sigma), obs=y)
    return m


def init():
    return {"K": 2500.0}


def fixed():
    return {"delta": DELTA}
'''

SCENE_PY = '''"""SCENE.py for `bayespd predict`: fracture_scene() returns a FractureScene whose params are
posterior variables of the calibration (here K and s0)."""
from bayespd.scenes.notched_plate import notched_plate


def fracture_scene():
    return notched_plate(side=16.0, h=1.0, steps=20, sigma=100.0)
'''

K_TRUE, NOISE = 3000.0, 0.01  # MPa; noise sd relative to the largest displacement


def write_inputs(folder, seed: int = 0) -> dict:
    """Write model.py, scene.py and data.npz (y at the model's points, from the h = 0.5
    grid at K_TRUE plus 1 % noise) into ``folder``; returns their paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {"model": folder / "model.py", "scene": folder / "scene.py", "data": folder / "data.npz"}
    for key, text in (("model", MODEL_PY), ("scene", SCENE_PY)):
        with atomic_path(paths[key]) as tmp:
            tmp.write_text(text)
    spec = importlib.util.spec_from_file_location("bayespd_demo_model", paths["model"])
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    points = module.scene().observation.points
    fine = module.scene(h=0.5, points=points)
    with torch.no_grad():
        clean = fine.observe(fine.solve({"K": K_TRUE, "delta": module.DELTA})).numpy()
    rng = np.random.default_rng(seed)
    y = clean + NOISE * np.abs(clean).max() * rng.standard_normal(clean.shape)
    with atomic_path(paths["data"]) as tmp, open(tmp, "wb") as f:
        np.savez(f, y=y)
    return paths
