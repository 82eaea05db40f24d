import numpy as np
import pytest
import torch

import bayespd as bp

torch.set_default_dtype(torch.float64)
torch.set_num_threads(1)  # small problems: threads only add overhead on 2 cores


def plate_scene(nx=10, ny=6, h=1.0, delta_max=2.5, material="lps", plane="stress"):
    """A small plate clamped on the left and pulled (and sheared) on the right."""
    p = bp.grid_2d(nx * h, ny * h, h)
    bonds = bp.find_bonds(p, delta_max)
    mat = (bp.LPS if material == "lps" else bp.BondBased)(p, bonds, plane=plane)
    obs = bp.Observation(p, p.x[~p.layer("left", delta_max)])
    return bp.Scene(mat, [bp.Dirichlet.layer(p, "left", delta_max)],
                    [bp.Load(p.layer("right", h), (30.0, 10.0))], obs)


@pytest.fixture
def small_scene():
    return plate_scene()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
