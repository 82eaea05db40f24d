"""models/md_kernel.py on synthetic periodic PD data (tests/learn/test_kernel.py's sheet): the
likelihood is stationary at the truth and the log density's Hessian (the Laplace precision) is
finite and negative definite there (for D = exp(d) apart from D's free scale; the sign-changing
kernel's shape coordinates have none)."""
import numpy as np
import pytest
import torch
from pyro import poutine
from pyro.infer.autoguide.initialization import init_to_value

from bayespd.infer.mode import grad_or_refused
from bayespd.infer.space import Unconstrained
from bayespd.learn.kernel import lps_params
from bayespd.learn.kernel_shape import KernelShape
from bayespd.materials import ParameterRangeError
from bayespd.models.md_kernel import md_kernel
from tests.learn.test_kernel import MODES, sheet, sinusoidal_forces

LAM, MU, D = -1.0, 3.0, [0.5, 2.0, 1.0]


def log_density(model, y, values, site=None):
    """The model's log density at ``values`` (only ``site``'s term when given)."""
    trace = poutine.trace(poutine.condition(model, data=values)).get_trace(y)
    return trace.log_prob_sum() if site is None else trace.nodes[site]["fn"].log_prob(y).sum()


def test_likelihood_is_stationary_and_the_precision_definite_at_the_truth():
    s = sheet()
    delta = 2.6 * s.material.particles.h
    f = sinusoidal_forces(s, MODES)
    y = s.spectral_solve(lps_params(LAM, MU, D, delta), f).detach()
    scales = y.pow(2).mean((1, 2)).sqrt()
    model = md_kernel(s, f, scales, nominal=MU)
    names = ("lam_plus_mu", "mu", "delta")

    def at(z, site=None):  # z = (log(lam + mu), log mu, delta, log D), sigma fixed
        return log_density(model, y, {"lam_plus_mu": torch.exp(z[0]), "mu": torch.exp(z[1]), "delta": z[2],
                                      "d": z[3:], "sigma": torch.tensor(0.01)}, site)

    truth = torch.tensor([np.log(LAM + MU), np.log(MU), delta, *np.log(D)])
    H = torch.autograd.functional.hessian(at, truth)
    assert bool(torch.isfinite(H).all())
    # the log coefficients' common shift is free (only D's shape matters): project it out
    shift = torch.cat([torch.zeros(3), torch.ones(3) / np.sqrt(3)])
    P = torch.eye(6) - torch.outer(shift, shift)
    eig = torch.linalg.eigvalsh(-P @ H @ P)
    assert eig[0].abs() < 1e-6 * eig[-1] and bool((eig[1:] > 0).all())
    z = truth.clone().requires_grad_(True)
    grad = torch.autograd.grad(at(z, "y"), z)[0]  # the likelihood is stationary at the truth
    assert float(grad.abs().max()) < 1e-6 * float(H.abs().max())


def test_scales_must_be_one_positive_rms_per_load():
    s = sheet()
    f = sinusoidal_forces(s, MODES)
    with pytest.raises(ValueError, match="one positive RMS per load"):
        md_kernel(s, f, torch.ones(2), nominal=1.0)


def sign_changing(s, delta):
    """(y, model, the truth's values) of the sign-changing model on noise-free data."""
    f = sinusoidal_forces(s, MODES)
    y = s.spectral_solve(lps_params(LAM, MU, D, delta), f).detach()
    model = md_kernel(s, f, y.pow(2).mean((1, 2)).sqrt(), nominal=MU, positive_kernel=False)
    truth = {"lam_plus_mu": torch.tensor(LAM + MU), "mu": torch.tensor(MU), "delta": torch.tensor(delta),
             "shape": KernelShape(s.material.influence).coordinates(torch.tensor(D)), "sigma": torch.tensor(0.01)}
    return y, model, truth


def test_the_sign_changing_kernel_has_no_free_direction():
    """D on the plane of normalised kernels (learn.kernel_shape): the log density's Hessian at
    the truth is negative definite with nothing projected out (the old D = d ~ N(0, I) had a
    direction, D's scale, seen by the prior alone), and the likelihood is stationary there."""
    s = sheet()
    y, model, truth = sign_changing(s, 2.6 * s.material.particles.h)

    def at(z, site=None):  # z = (log(lam + mu), log mu, delta, shape), sigma fixed
        return log_density(model, y, {**truth, "lam_plus_mu": torch.exp(z[0]), "mu": torch.exp(z[1]),
                                      "delta": z[2], "shape": z[3:]}, site)

    z0 = torch.cat([torch.log(truth["lam_plus_mu"])[None], torch.log(truth["mu"])[None], truth["delta"][None],
                    truth["shape"]])
    H = torch.autograd.functional.hessian(at, z0)
    eig = torch.linalg.eigvalsh(-H)
    assert bool((eig > 1e-8 * eig[-1]).all())
    z = z0.clone().requires_grad_(True)
    grad = torch.autograd.grad(at(z, "y"), z)[0]
    assert float(grad.abs().max()) < 1e-6 * float(H.abs().max())


def test_an_inadmissible_kernel_is_a_refused_point_of_the_map_search():
    """Far along a direction of the plane whose discrete weighted volume is negative (the
    continuous moment is the plane's, the lattice sum is not), m < 0: the model raises a
    ParameterRangeError there (UnsolvableKernel), which the MAP search takes as an infinite
    potential (a rejected trial point), while the truth evaluates finitely."""
    s = sheet()
    delta = 2.6 * s.material.particles.h
    y, model, good = sign_changing(s, delta)
    plane, material = KernelShape(s.material.influence), s.material
    moment = torch.stack([(material.bond_weight({"D": n, "delta": torch.tensor(delta)}) * material.length**2).sum()
                          for n in plane.basis.T])
    j = int(moment.abs().argmax())
    bad = {**good, "shape": -1e6 * torch.sign(moment[j]) * torch.eye(plane.dim, dtype=moment.dtype)[j]}
    with pytest.raises(ParameterRangeError, match="not admissible"):
        log_density(model, y, bad)
    space = Unconstrained(model, {"y": y}, init_to_value(values=good))
    u, g = grad_or_refused(space, space.initial)
    assert np.isfinite(float(u)) and g is not None
    assert grad_or_refused(space, space.unconstrain(bad).reshape(-1)) == (np.inf, None)
