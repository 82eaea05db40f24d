"""A ready-made fracture scene: a square bond-based plate (plane stress, Dodwell 2019 eq 1) with a
notch from the left edge to the centre, bottom layer clamped, top layer pulled up by lambda
(mode I), white Brownian forcing C = sigma^2 I (eq 4) and the sharp critical stretch (eq 2).
Posterior parameters: the bulk modulus ``K`` and the critical stretch ``s0``.

The mobility M = sigma^2 / eta is set so that M dt lambda_min(A) = ``relax`` (one step relaxes
the elastic field); the bond-based operator is linear in K (c = 9 K / (pi t delta^3)), so
lambda_min(A; K) = K lambda_min(A; 1), found once per process. The force is linear in K too,
so eq 4 at K is eq 4 of the unit-modulus body at temperature eta / K = sigma^2 dt
lambda_min(A; 1) / relax, which does not depend on K: every draw runs a ``Scene`` of the same
unit-modulus material (built once per process) with its own critical stretch, and the same step
operator, whose factor is made once per process (``trailing.shared``); only its reactions are
scaled by K.
"""
from __future__ import annotations

from functools import lru_cache, partial

import numpy as np
import scipy.sparse.linalg as sla
import torch

import bayespd as bp
from bayespd.damage import CriticalStretch
from bayespd.solvers import white_noise
from bayespd.solvers.fracture import StochasticFracture
from bayespd.solvers.quasistatic import quasi_static

from bayespd.ensemble.scene import FractureScene


@lru_cache(maxsize=4)
def _geometry(side: float, h: float, m: int):
    """Material (bonds with the notch cut) and the two Dirichlet layers, built once."""
    delta = m * h
    p = bp.grid_2d(side, side, h)
    bonds = bp.precrack(p, bp.find_bonds(p, delta), [[0.0, side / 2], [side / 2, side / 2]])
    bcs = (bp.Dirichlet.layer(p, "bottom", delta), bp.Dirichlet.layer(p, "top", delta, (0.0, 1.0)))
    return bp.BondBased(p, bonds), bcs, delta


def plate_scene(side, h, m, damage=None, sigma=None) -> bp.Scene:
    """The plate (top layer at unit displacement) with an optional damage law and white
    noise C = sigma^2 I; its params are {"K": ..., "delta": m h}."""
    material, bcs, _ = _geometry(side, h, m)
    noise = None if sigma is None else partial(_white_noise, sigma)
    return bp.Scene(material, list(bcs), damage=damage, noise=noise)


def _white_noise(sigma, dofs):
    return white_noise(sigma, len(dofs))


@lru_cache(maxsize=4)
def _unit_body(side, h, m):
    """The intact unit-modulus plate at fixed params (``Scene.at``), built once per process."""
    return plate_scene(side, h, m).at({"K": 1.0, "delta": m * h})


@lru_cache(maxsize=4)
def _unit_lambda_min(side, h, m) -> float:
    """lambda_min of the intact operator at K = 1 (shift-invert Lanczos from a fixed start
    vector: ARPACK's default random start changes the last bits from run to run)."""
    body = _unit_body(side, h, m)
    intact = torch.ones(body.n_bonds)
    A = body.operator(intact, body.active(intact))
    v0 = np.ones(A.shape[0])
    return float(sla.eigsh(A, k=1, sigma=0, v0=v0, return_eigenvectors=False)[0])


def plate_driver(params: dict, *, side, h, m, sigma, relax, dt) -> StochasticFracture:
    """The stochastic fracture driver at ``params = {"K": ..., "s0": ...}``: the unit-modulus
    plate at temperature sigma^2 dt lambda_min(A; 1) / relax, its reactions times K (module
    docstring)."""
    K, s0 = params["K"], params["s0"]
    if not (K > 0 and s0 > 0):
        raise ValueError(f"K and s0 must be positive, got K={K}, s0={s0}")
    eta = sigma**2 * dt * _unit_lambda_min(side, h, m) / relax
    return StochasticFracture(plate_scene(side, h, m, CriticalStretch(s0), sigma), {"K": 1.0, "delta": m * h},
                              eta=eta, reaction_scale=K)


def notched_plate(side: float = 40.0, h: float = 1.0, m: int = 3, s0_nominal: float = 0.0094,
                  steps: int = 50, reach: float = 2.0, sigma: float = 1500.0, relax: float = 1e4,
                  dt: float = 1.0, observed_path=None, tangent: str = "lagged",
                  band: float | None = 8.0) -> FractureScene:
    """The scene: ``steps`` top displacements up to ``reach`` times the elastic estimate of
    initiation at ``s0_nominal`` (s0 / max stretch at unit displacement, independent of K);
    failure when the crack has run through half the ligament (side / 4). Paths are traced at
    phi > 0.3: the faces of a straight crack have phi = 0.44 at delta = 3h, of a kinked one
    0.3-0.4, and 0.4 would cut a kinked path apart (``experiments/crack_paths.py``).
    ``tangent``: "lagged" by default, 2.1x faster than "exact" at 10k particles, its mean
    outcomes within one standard error of the exact tangent's (``benchmarks/fracture.py``).
    ``band``: the crack zone (ordered last in the factor) is the ligament ahead of the notch
    tip, from one horizon behind it, ``band`` spacings either side of the notch line (the
    paths of ``experiments/crack_ensemble.py`` stay within 4 h of it; None: no zone). With
    the zone, the Woodbury columns cost no solves, and a rank up to 1024 keeps a run on one
    factorisation (512: two, ``benchmarks/fracture.py``)."""
    if not (side > 0 and h > 0 and side / h >= 8 and int(m) == m and m >= 2):
        raise ValueError("need side >= 8 h, h > 0 and an integer horizon factor m >= 2")
    body = _unit_body(side, h, m)
    unit = quasi_static(plate_scene(side, h, m), {"K": 1.0, "delta": m * h}, [1e-3]).u / 1e-3
    initiation = s0_nominal / float(body.kinematics.stretch(unit).max())
    lams = np.linspace(reach / steps, reach, steps) * initiation
    x = np.asarray(body.particles.x)
    zone = None if band is None else ((x[:, 0] >= side / 2 - m * h) & (np.abs(x[:, 1] - side / 2) <= band * h))
    build = partial(plate_driver, side=float(side), h=float(h), m=int(m), sigma=float(sigma),
                    relax=float(relax), dt=float(dt))
    return FractureScene(build, ("K", "s0"), lams, dt, x,
                         origin=(side / 2, side / 2), direction=(1.0, 0.0),
                         failure_length=side / 4, load_component=1, path_threshold=0.3,
                         observed_path=observed_path, tangent=tangent, zone=zone,
                         max_rank=512 if zone is None else 1024,
                         attrs={"scene": "notched_plate", "side": side, "h": h, "m": m,
                                "sigma": sigma, "relax": relax})
