"""Energy-based surface correction: the free-edge boundary layer of a plate in uniaxial
tension shrinks, the bulk is untouched, and the corrected solve stays differentiable."""
import numpy as np
import pytest
import torch

import bayespd as bp

E, NU, STRAIN = 4000.0, 0.3, 1e-3


def tension(material, correction, length=60.0, width=30.0, m=3):
    """Displacement-controlled uniaxial tension with u_y free at the ends (one row pinned):
    the classical answer is affine. Returns the rows' mean |u_y - affine fit of the core| /
    (strain * width / 2) from the free edge inwards, along the middle third of the plate."""
    p = bp.grid_2d(length, width, 1.0)
    delta = float(m)
    cls = bp.LPS if material == "lps" else bp.BondBased
    mat = cls(p, bp.find_bonds(p, delta), surface_correction=correction)
    ends = p.layer("left", delta) | p.layer("right", delta)
    yc = width / 2
    pin = p.layer("left", delta) & (np.abs(p.x[:, 1] - yc) < 1.0)
    params = {"K": E, "delta": delta} if material == "bb" else dict(zip("KG", bp.moduli_from_young(E, NU)), delta=delta)
    scene = bp.Scene(mat, [bp.Dirichlet(ends, (STRAIN * p.x[ends, 0], None)), bp.Dirichlet(pin, (None, 0.0))],
                     [bp.Load(ends, (0.0, 0.0))])
    u = scene.solve(params).numpy()
    X = np.c_[np.ones(p.n), p.x]
    middle = np.abs(p.x[:, 0] - length / 2) < length / 6
    core = middle & (np.abs(p.x[:, 1] - yc) < yc - 3 * delta)
    affine = X @ np.linalg.lstsq(X[core], u[core], rcond=None)[0]
    depth = yc - np.abs(p.x[:, 1] - yc)  # distance of the particle centre from the free edge
    err = np.abs(u - affine)[:, 1] / (STRAIN * yc)
    return np.array([err[middle & (np.abs(depth - (k + 0.5)) < 1e-9)].mean() for k in range(2 * m)])


@pytest.mark.parametrize("material", ["lps", "bb"])
def test_boundary_layer_error_shrinks(material):
    """Measured (m = 3, h = 1): the worst row within one horizon of the free edge drops from
    1.3 % to 0.87 % (LPS) and from 1.05 % to 0.67 % (bond-based); we require a 20 % drop of
    the worst row and of the RMS over the layer, and no change deeper than 2 delta."""
    plain, corrected = tension(material, False), tension(material, True)
    layer = slice(0, 3)
    assert corrected[layer].max() < 0.8 * plain[layer].max()
    assert np.sqrt((corrected[layer] ** 2).mean()) < 0.8 * np.sqrt((plain[layer] ** 2).mean())
    assert corrected[3:].max() < 1e-3 and plain[3:].max() < 1e-3


def test_correction_is_one_in_the_bulk_and_differentiable():
    """Bonds whose two ends have complete families keep the factor 1 exactly (the bulk is
    referred to its own lattice, so its calibration is untouched), for both materials and a
    non-constant influence function; the corrected solve passes gradcheck in K, G and delta."""
    from bayespd.surface import bond_factors

    p = bp.grid_2d(20.0, 20.0, 1.0)
    bonds = bp.find_bonds(p, 3.0)
    K, G = bp.moduli_from_young(E, NU)
    complete = np.all((p.x > 3.5) & (p.x < 16.5), axis=1)
    inner = torch.as_tensor(complete[bonds.i] & complete[bonds.j])
    for mat, moduli in [(bp.LPS(p, bonds, influence=bp.Conical()), {"K": K, "G": G}),
                        (bp.BondBased(p, bonds), {"K": K})]:
        factor = bond_factors(mat, mat.moduli(dict(moduli, delta=2.7)), {"delta": 2.7})
        assert float((factor[inner] - 1).abs().max()) < 1e-12
        assert float((factor[~inner] - 1).abs().max()) > 0.05

    p = bp.grid_2d(7.0, 5.0, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 2.5), surface_correction=True)
    scene = bp.Scene(mat, [bp.Dirichlet.layer(p, "left", 2.5)], [bp.Load(p.layer("right", 1.0), (30.0, 10.0))])
    theta = [torch.tensor(v, requires_grad=True) for v in (3000.0, 1400.0, 2.2)]
    f = lambda K, G, d: scene.solve({"K": K, "G": G, "delta": d})[-2:]  # noqa: E731
    assert torch.autograd.gradcheck(f, theta, eps=1e-6, atol=1e-8, rtol=1e-5)
