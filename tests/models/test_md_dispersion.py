"""models/md_dispersion.py: its likelihood is the density of the measured compliances by the change
of variables C = L^-T (I + Delta) L^-1 (checked against the Gaussian of C's entries, to rounding);
the common offset's limit tau -> 0 is the per-orbit law and its conditional posterior
(bayespd.learn.dispersion) is Bayes' rule on log_prob's own scalings; with a measurement error the
model's density is the dense Gaussian of every orbit's entries; shells without an orbit are refused."""
import numpy as np
import pytest
import torch
from pyro import poutine
from torch.distributions import MultivariateNormal

from bayespd.learn.dispersion import common_offset_posterior, common_offset_prior, relative_compliance_error
from bayespd.learn.kernel_shape import KernelShape
from bayespd.models.md_dispersion import CompliancePerOrbit, md_dispersion
from tests.learn.test_dispersion import D, LAM, MU, pd_sheet

WAVES = np.array([[1, 0], [1, 1], [2, 1]])


def symbols_and_data(seed=0):
    s, n, p = pd_sheet()
    S = s.symbol(p, torch.as_tensor(WAVES * 2 * np.pi / s.box)).detach()
    off = torch.tensor([False, True, True])
    law = CompliancePerOrbit(S, torch.tensor([0.03, 0.05, 0.02], dtype=S.dtype), off)
    torch.manual_seed(seed)
    return s, S, off, law, law.sample()


def test_the_likelihood_is_the_density_of_the_compliance():
    """Per orbit, (C11, C22[, C12]) is Gaussian with mean S^-1's entries and covariance J Sigma J^T
    (J = dC/dDelta: linear, Sigma = diag(s^2, s^2[, s^2 / 2])): the sum of those log densities
    equals log_prob to rounding."""
    _, S, off, law, C = symbols_and_data()
    total = 0.0
    for o in range(len(S)):
        Linv = torch.linalg.inv(torch.linalg.cholesky(S[o]))
        entries = [(0, 0), (1, 1), (0, 1)][: 3 if off[o] else 2]

        def c_of(d):  # the measured entries for Delta's entries d
            D = torch.zeros(2, 2, dtype=S.dtype)
            for (i, j), v in zip(entries, d):
                D = D + v * (torch.eye(2, dtype=S.dtype)[i][:, None] * torch.eye(2, dtype=S.dtype)[j][None, :])
                if i != j:
                    D = D + v * (torch.eye(2, dtype=S.dtype)[j][:, None] * torch.eye(2, dtype=S.dtype)[i][None, :])
            X = Linv.T @ (torch.eye(2, dtype=S.dtype) + D) @ Linv
            return torch.stack([X[i, j] for i, j in entries])

        zero = torch.zeros(len(entries), dtype=S.dtype)
        J = torch.autograd.functional.jacobian(c_of, zero)
        sd = law.s[o] ** 2 * torch.tensor([1.0, 1.0, 0.5][: len(entries)], dtype=S.dtype)
        total += MultivariateNormal(c_of(zero), J @ torch.diag(sd) @ J.T).log_prob(
            torch.stack([C[o][i, j] for i, j in entries]))
    assert abs(float(law.log_prob(C)) - float(total)) < 1e-9 * abs(float(total))


def test_a_vanishing_common_offset_is_the_per_orbit_law():
    _, S, off, law, C = symbols_and_data()
    tiny = CompliancePerOrbit(S, law.s, off, torch.tensor(1e-9, dtype=S.dtype))
    assert abs(float(tiny.log_prob(C)) - float(law.log_prob(C))) < 1e-8 * abs(float(law.log_prob(C)))


def test_the_common_offset_posterior_is_bayes_rule_on_the_likelihood():
    """For any offset c: log p_tau(C) = log prior(c) + log p(C | c) - log posterior(c | C), where
    p(C | c) is the per-orbit law of Delta - c (same Jacobian det S^(q/2)) and prior / posterior
    the 3-entry normals of learn.dispersion: to 1e-10 relative at three values of c, so the
    posterior uses CompliancePerOrbit's entry scalings (tau, tau / sqrt 2)."""
    _, S, off, law, _ = symbols_and_data()
    tau = torch.tensor(0.04, dtype=S.dtype)
    C = CompliancePerOrbit(S, law.s, off, tau).sample()
    Delta, _ = relative_compliance_error(S, C)
    post, prior = common_offset_posterior(Delta, law.s, float(tau), off), common_offset_prior(float(tau))
    joint = float(CompliancePerOrbit(S, law.s, off, tau).log_prob(C))
    Linv = torch.linalg.inv(torch.linalg.cholesky(S))
    for c in (post.mean, post.mean + 0.01, torch.tensor([[0.03, -0.02], [-0.02, 0.01]], dtype=S.dtype)):
        shifted = Linv.transpose(-1, -2) @ (torch.eye(2, dtype=S.dtype) + Delta - c) @ Linv

        def log_normal(law_c):
            return sum(float(torch.distributions.Normal(law_c.mean[i, j], law_c.sd[i, j]).log_prob(c[i, j]))
                       for i, j in ((0, 0), (1, 1), (0, 1)))

        total = log_normal(prior) + float(law.log_prob(shifted)) - log_normal(post)
        assert abs(total - joint) < 1e-10 * abs(joint)


def test_shells_must_each_hold_an_orbit():
    s, _, _ = pd_sheet()
    with pytest.raises(ValueError, match="every shell needs an orbit"):
        md_dispersion(s, WAVES * 2 * np.pi / s.box, torch.tensor([False, True, True]), (1e-3, 2e-3), nominal=3.0)


def test_the_measurement_error_density_is_the_dense_gaussian():
    """md_dispersion with a measurement error sigma_m: the measured entries of every orbit are one
    Gaussian, Delta = A c + eps + m (c the common offset, sd w_e tau; eps and m per orbit, sd w_e s_o
    and w_e sigma_m; w_e = 1, 1, 1 / sqrt 2 for 00, 11, 01) mapped by each orbit's linear
    C = L^-T (I + Delta) L^-1: the C site's log density equals that dense normal's to 1e-9
    relative, and the model without sigma_m differs from it by 1e6 times that (the term is used)."""
    sheet, _, p = pd_sheet()
    h = sheet.material.particles.h
    k = torch.as_tensor(WAVES * 2 * np.pi / sheet.box)
    kh = k.norm(dim=1).numpy() * h
    shells, off = ((kh[0] + kh[2]) / 2,), torch.tensor([False, True, True])
    s_b, tau, sigma = torch.tensor([0.03, 0.05], dtype=k.dtype), 0.02, 0.04
    values = {"lam_plus_mu": torch.tensor(LAM + MU, dtype=k.dtype), "mu": torch.tensor(MU, dtype=k.dtype),
              "delta": p["delta"], "shape": KernelShape(sheet.material.influence).coordinates(D), "s": s_b,
              "tau": torch.tensor(tau, dtype=k.dtype)}

    def log_density(measurement, C):
        model = md_dispersion(sheet, k, off, shells, nominal=3.0, measurement=measurement)
        trace = poutine.trace(poutine.condition(model, data=values)).get_trace(C)
        return trace.nodes["C"]["fn"], float(trace.nodes["C"]["fn"].log_prob(trace.nodes["C"]["value"]))

    law, _ = log_density(sigma, None)
    S, shell = law.S.detach(), (torch.as_tensor(kh) > shells[0]).long()
    torch.manual_seed(2)
    C = law.sample()
    rows, cols, noise, blocks, mean = [], [], [], [], []
    scale = {(0, 0): 1.0, (1, 1): 1.0, (0, 1): np.sqrt(0.5)}
    for o in range(len(S)):
        Linv = torch.linalg.inv(torch.linalg.cholesky(S[o])).numpy()
        entries = [(0, 0), (1, 1), (0, 1)][: 3 if off[o] else 2]
        J = np.zeros((len(entries), len(entries)))  # d C_entry / d Delta_entry (Delta symmetric)
        for b, (i, j) in enumerate(entries):
            E = np.zeros((2, 2))
            E[i, j] = E[j, i] = 1.0
            X = Linv.T @ E @ Linv
            J[:, b] = [X[a, c] for a, c in entries]
        blocks.append(J)
        mean += [(Linv.T @ Linv)[a, c] for a, c in entries]
        for e in entries:
            rows.append([(0, 0), (1, 1), (0, 1)].index(e))
            noise.append(scale[e] ** 2 * (float(s_b[shell[o]]) ** 2 + sigma**2))
            cols.append(float(C[o][e]))
    A = np.eye(3)[rows]
    cov_delta = A @ np.diag([tau**2, tau**2, tau**2 / 2]) @ A.T + np.diag(noise)
    J = np.zeros((len(rows), len(rows)))
    at = 0
    for b in blocks:
        J[at:at + len(b), at:at + len(b)] = b
        at += len(b)
    dense = MultivariateNormal(torch.as_tensor(mean), torch.as_tensor(J @ cov_delta @ J.T)).log_prob(torch.as_tensor(cols))
    _, got = log_density(sigma, C)
    assert abs(got - float(dense)) < 1e-9 * abs(float(dense))
    assert abs(got - log_density(0.0, C)[1]) > 1e-3 * abs(float(dense))  # a million times the match's tolerance
    with pytest.raises(ValueError, match="non-negative"):
        md_dispersion(sheet, k, off, shells, nominal=3.0, measurement=-0.01)
