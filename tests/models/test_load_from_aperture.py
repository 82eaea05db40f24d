"""models/load_from_aperture.py: F_y of Turner 2015 §5 from crack apertures.

A 2.4 x 2.4 mm plate (plane strain, k = 66.7 GPa, mu = 40 GPa, delta = 0.3 mm), an edge crack
a = 0.6 mm at mid-height, bottom strip 2 delta fixed, F_y on the top strip 2 delta. Data: the
same body on a grid twice as fine (h = 0.05 mm, same horizon), openings at 6 stations, noise
of 2 % of the largest opening. The posterior is essentially Gaussian in F_y (the openings are
linear in it), of sd ~0.9 % here; the discretisation error (h vs h/2, noise-free least squares)
biases F_y by 0.45 %, half a posterior sd, so the 90 % interval still covers the truth with
probability ~0.85; at 1 % noise the bias would be ~1 sd and coverage would fail often, which is
the honest limit of a 6-station calibration. The mean must lie within 3 sd and 3 % of the truth.
"""
import numpy as np
import pyro.distributions as dist
import pytest
import torch

import bayespd as bp
from bayespd import linalg
from bayespd.infer import fit
from bayespd.models.load_from_aperture import aperture_observation, load_from_aperture

SIDE, A, Y_CRACK, DELTA, F_TRUE = 2.4, 0.6, 1.2, 0.3, 60.0
MODULI = {"K": 66700.0, "G": 40000.0}
STATIONS = np.arange(0.05, A, 0.1)
ABOVE = np.stack([STATIONS, np.full_like(STATIONS, Y_CRACK + 0.05)], 1)
BELOW = np.stack([STATIONS, np.full_like(STATIONS, Y_CRACK - 0.05)], 1)


def plate(h):
    p = bp.grid_2d(SIDE, SIDE, h)
    bonds = bp.precrack(p, bp.find_bonds(p, DELTA), [[-h, Y_CRACK], [A, Y_CRACK]])
    return bp.Scene(bp.LPS(p, bonds, plane="strain"), [bp.Dirichlet.layer(p, "bottom", 2 * DELTA)],
                    [bp.Load(p.layer("top", 2 * DELTA), (0.0, 1.0))], aperture_observation(p, ABOVE, BELOW))


@pytest.fixture(scope="module", autouse=True)
def one_factor_thread():
    """Threaded CHOLMOD crawls on a shared 2-core machine (see experiments/tikhonov_aperture.py)."""
    with linalg.settings(factor_threads=1):
        yield


@pytest.fixture(scope="module")
def problem(one_factor_thread):
    fine = plate(0.05)
    with torch.no_grad():
        clean = fine.observe(fine.solve(dict(MODULI, delta=DELTA, load=F_TRUE)))
    sd = 0.02 * float(clean[:, 1].abs().max())
    y = clean + sd * torch.randn(clean.shape, generator=torch.Generator().manual_seed(0))
    return plate(0.1), y, sd


def test_posterior_of_the_load_covers_the_truth(problem):
    scene, y, sd = problem
    model = load_from_aperture(scene, 30.0, 5 * sd, dict(MODULI, delta=DELTA))
    tree = fit(model, {"y": y}, "laplace", num_samples=300, seed=0, scene=scene, progress=False)
    F = tree["posterior"]["load"].values.ravel()
    lo, hi = np.quantile(F, [0.05, 0.95])
    assert abs(F.mean() - F_TRUE) < min(3 * F.std(), 0.03 * F_TRUE), (F.mean(), F.std())
    assert lo <= F_TRUE <= hi, (lo, hi)


def test_bad_input_is_refused(problem):
    scene, y, sd = problem
    fixed = dict(MODULI, delta=DELTA)
    with pytest.raises(ValueError, match=r"fixed must give exactly \['G', 'K', 'delta'\]"):
        load_from_aperture(scene, 30.0, sd, {"K": 1.0, "delta": DELTA})
    with pytest.raises(ValueError, match="delta"):
        load_from_aperture(scene, 30.0, sd, dict(MODULI, delta=0.05))
    with pytest.raises(ValueError, match="fixed K must be finite and positive"):
        load_from_aperture(scene, 30.0, sd, dict(fixed, K=-1.0))
    with pytest.raises(ValueError, match=r"prior of load .*negative values.*LogNormal"):
        load_from_aperture(scene, 30.0, sd, fixed, priors={"load": dist.Normal(30.0, 10.0)})
    with pytest.raises(ValueError, match="nominal load must be finite and positive"):
        load_from_aperture(scene, 0.0, sd, fixed)
    model = load_from_aperture(scene, 30.0, sd, fixed)
    with pytest.raises(ValueError, match=r"y has shape \(5, 2\) but the model predicts \(6, 2\)"):
        model(y[:-1])
    with pytest.raises(ValueError, match="matching"):
        aperture_observation(scene.particles, ABOVE, BELOW[:-1])
