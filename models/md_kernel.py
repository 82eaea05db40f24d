"""The Bayesian version of paper 004's kernel learning (phase 1, eqs 4.2-4.7): a posterior over the
2D moduli, the horizon and the shape of a Bernstein kernel from periodic sheets.

    lambda + mu ~ LogNormal(log nominal, 1),   mu ~ LogNormal(log nominal, 1)
    delta       ~ ScaledBeta(1.2 h, delta_max, 2, 2)
    d_k         ~ Normal(0, 1),  D = exp(d)    (P + 1 log-coefficients; only the shape matters)
    or, for a sign-changing kernel (eq 4.2's D_k in R):
    shape       ~ MultivariateStudentT(1, 0, rho I_P),  D = D_0 + N shape   (learn.kernel_shape)
    sigma       ~ HalfNormal(0.1)              (relative noise)
    y[m]        ~ Normal(u_m(lambda, mu, D, delta), sigma * scale_m)   zero-mean displacements

u_m is ``PeriodicSheet.spectral_solve`` under the nodal forces of load m and scale_m the RMS of
load m's data, so sigma is a relative error as in ``bayespd.learn.kernel``. The solvability
constraint (eq 4.4) enters as the factor -N ``solvability_penalty`` (N: the nodes), the misfit's
penalty in likelihood units; a kernel with m <= 0 is a rejected trial point.

The sign-changing kernel takes P identified coordinates on the plane of normalised kernels, not
D = d ~ N(0, I_(P+1)): the likelihood does not see D's scale, and along it N(0, I) has its mode at
the inadmissible D = 0, so that model has no MAP (its Laplace step was centred wherever the search
stopped, and a leftover gradient g of the likelihood made the Hessian indefinite through
H d = -g, the identity of a scale-free function). The Cauchy prior on the plane is the one
the old prior gave the shape (a uniform direction), so the posterior over kernel shapes (those
with a positive moment, which m > 0 needs) is the same.
"""
from __future__ import annotations

import math

import pyro
import pyro.distributions as dist
import torch

from bayespd.infer import ScaledBeta
from bayespd import KernelShape, lps_params, solvability_penalty
from bayespd.models.observations import check_shape
from bayespd.models.priors import positive


def kernel_prior(sheet, nominal: float, positive_kernel: bool = True):
    """``draw()``: the LPS params (plane strain) of the sites ``lam_plus_mu``, ``mu``, ``delta``,
    ``d`` (or ``shape``) under the priors above; ``nominal``: the prior median of lambda + mu and mu."""
    m = math.log(positive("the nominal modulus", nominal))
    h, delta_max = sheet.material.particles.h, sheet.material.bonds.delta_max
    P = sheet.material.influence.degree
    plane = None if positive_kernel else KernelShape(sheet.material.influence)

    def draw() -> dict:
        kappa = pyro.sample("lam_plus_mu", dist.LogNormal(m, 1.0))
        mu = pyro.sample("mu", dist.LogNormal(m, 1.0))
        delta = pyro.sample("delta", ScaledBeta(1.2 * h, delta_max, 2.0, 2.0))
        if positive_kernel:
            D = torch.exp(pyro.sample("d", dist.Normal(torch.zeros(P + 1), 1.0).to_event(1)))
        else:
            D = plane.coefficients(pyro.sample("shape", dist.MultivariateStudentT(
                torch.tensor(1.0), torch.zeros(P), plane.uniform_direction_scale * torch.eye(P))))
        return lps_params(kappa - mu, mu, D, delta)

    return draw


def md_kernel(sheet, forces, scales, nominal: float, positive_kernel: bool = True):
    """A Pyro model ``model(y=None)`` for zero-mean displacements y (loads, N, 2) of ``sheet`` under
    nodal ``forces`` (loads, N, 2); ``scales`` (loads,): each load's data RMS; ``nominal``: the
    prior median of lambda + mu and mu; ``positive_kernel=False``: a sign-changing D at coordinates
    ``shape`` of ``KernelShape(sheet.material.influence)``. Sites ``lam_plus_mu``, ``mu``,
    ``delta``, ``d`` (or ``shape``), ``sigma``."""
    forces, scales = torch.as_tensor(forces), torch.as_tensor(scales)
    shape = tuple(forces.shape)
    if scales.shape != shape[:1] or not bool(torch.all(scales > 0)):
        raise ValueError(f"scales must hold one positive RMS per load ({shape[0]})")
    draw = kernel_prior(sheet, nominal, positive_kernel)

    def model(y=None):
        if y is not None:
            y = check_shape(y, shape, "y", "the zero-mean nodal displacements of every load")
        params = draw()
        sigma = pyro.sample("sigma", dist.HalfNormal(0.1))
        pyro.factor("solvability", -forces[..., 0].numel() * solvability_penalty(sheet, params))
        u = sheet.spectral_solve(params, forces)
        pyro.sample("y", dist.Normal(u, sigma * scales[:, None, None]).to_event(3), obs=y)

    return model
