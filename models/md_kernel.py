"""The Bayesian version of paper 004's kernel learning (phase 1, eqs 4.2-4.7): a posterior over the
2D moduli, the horizon and the shape of a Bernstein kernel from periodic sheets.

    lambda + mu ~ LogNormal(log nominal, 1),   mu ~ LogNormal(log nominal, 1)
    delta       ~ ScaledBeta(1.2 h, delta_max, 2, 2)
    d_k         ~ Normal(0, 1),  D = exp(d)    (P + 1 log-coefficients; only the shape matters;
                                               or D = d, a sign-changing kernel)
    sigma       ~ HalfNormal(0.1)              (relative noise)
    y[m]        ~ Normal(u_m(lambda, mu, D, delta), sigma * scale_m)   zero-mean displacements

u_m is ``PeriodicSheet.spectral_solve`` under the nodal forces of load m and scale_m the RMS of
load m's data, so sigma is a relative error as in ``bayespd.learn.kernel``. The solvability
constraint (eq 4.4) enters as the factor -N ``solvability_penalty`` (N: the nodes), the misfit's
penalty in likelihood units; a kernel with m <= 0 is a rejected trial point.
"""
from __future__ import annotations

import math

import pyro
import pyro.distributions as dist
import torch

from bayespd.infer import ScaledBeta
from bayespd import lps_params, solvability_penalty
from bayespd.models.observations import check_shape
from bayespd.models.priors import positive


def md_kernel(sheet, forces, scales, nominal: float, positive_kernel: bool = True):
    """A Pyro model ``model(y=None)`` for zero-mean displacements y (loads, N, 2) of ``sheet`` under
    nodal ``forces`` (loads, N, 2); ``scales`` (loads,): each load's data RMS; ``nominal``: the
    prior median of lambda + mu and mu; ``positive_kernel=False``: D = d (eq 4.2's D_k in R, the
    prior then holding D's free scale near 1). Sites ``lam_plus_mu``, ``mu``, ``delta``, ``d``, ``sigma``."""
    forces, scales = torch.as_tensor(forces), torch.as_tensor(scales)
    shape = tuple(forces.shape)
    if scales.shape != shape[:1] or not bool(torch.all(scales > 0)):
        raise ValueError(f"scales must hold one positive RMS per load ({shape[0]})")
    m = math.log(positive("the nominal modulus", nominal))
    h, delta_max = sheet.material.particles.h, sheet.material.bonds.delta_max
    P = sheet.material.influence.degree

    def model(y=None):
        if y is not None:
            y = check_shape(y, shape, "y", "the zero-mean nodal displacements of every load")
        kappa = pyro.sample("lam_plus_mu", dist.LogNormal(m, 1.0))
        mu = pyro.sample("mu", dist.LogNormal(m, 1.0))
        delta = pyro.sample("delta", ScaledBeta(1.2 * h, delta_max, 2.0, 2.0))
        d = pyro.sample("d", dist.Normal(torch.zeros(P + 1), 1.0).to_event(1))
        sigma = pyro.sample("sigma", dist.HalfNormal(0.1))
        params = lps_params(kappa - mu, mu, torch.exp(d) if positive_kernel else d, delta)
        pyro.factor("solvability", -forces[..., 0].numel() * solvability_penalty(sheet, params))
        u = sheet.spectral_solve(params, forces)
        pyro.sample("y", dist.Normal(u, sigma * scales[:, None, None]).to_event(3), obs=y)

    return model
