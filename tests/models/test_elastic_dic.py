"""models/elastic_dic.py: K, G (delta, sigma) from a DIC field with a masked band.

Data: a grid twice as fine (same body, same horizon), observed at the DIC points by bilinear
interpolation, 1 % noise, a vertical band of the grid lost (NaN) and masked. The Laplace
posterior must cover the truth within 3 posterior sd (a 0.3 % chance miss for a Gaussian
posterior; a broken mask or likelihood biases K by many sd: the band holds 2 of 11 columns).
"""
import numpy as np
import pyro.distributions as dist
import pyro
import pytest
import torch

import bayespd as bp
from bayespd.infer import ScaledBeta, fit
from bayespd.models.elastic_dic import dic_data, elastic_dic

TRUTH = {"K": 3000.0, "G": 1400.0, "delta": 2.6}
POINTS = bp.grid_points((3.2, 0.6), 0.8, (11, 7))


def scene(h, delta_max, observation=bp.GridObservation):
    p = bp.grid_2d(12.0, 6.0, h)
    return bp.Scene(bp.LPS(p, bp.find_bonds(p, delta_max)), [bp.Dirichlet.layer(p, "left", 3.0)],
                    [bp.Load(p.layer("right", 1.0), (60.0, 20.0))], observation(p, POINTS))


@pytest.fixture(scope="module")
def problem():
    fine = scene(0.5, 2.6)
    with torch.no_grad():
        clean = fine.observe(fine.solve(TRUTH)).numpy()
    sigma = 0.01 * float(np.abs(clean).max())
    y = clean + sigma * np.random.default_rng(5).standard_normal(clean.shape)
    band = (POINTS[:, 0] > 6.0) & (POINTS[:, 0] < 7.5)
    y[band] = np.nan
    mask = np.repeat(~band[:, None], 2, axis=1)
    coarse = scene(1.0, 3.0)
    return coarse, y, mask, sigma


def test_laplace_recovers_moduli_with_a_masked_band(problem):
    coarse, y, mask, sigma = problem
    data = dic_data(coarse, y, mask)
    assert int(data["mask"].sum()) == 2 * 7 * 9  # 2 of the 11 columns lost
    model = elastic_dic(coarse, {"K": 2500.0, "G": 1200.0}, 0.05 * float(np.nanmax(np.abs(y))),
                        priors={"delta": ScaledBeta(2.3, 2.9)})
    tree = fit(model, data, "laplace", num_samples=500, seed=0, scene=coarse, progress=False)
    post = tree["posterior"]
    for k, truth in dict(TRUTH, sigma=sigma).items():
        if k == "delta":
            continue
        draws = post[k].values.reshape(-1)
        assert abs(draws.mean() - truth) < 3 * draws.std(), (k, draws.mean(), draws.std(), truth)
    # the band's entries carry no likelihood
    ll = tree["log_likelihood"]["y"].values
    assert np.all(ll[..., ~data["mask"].numpy()] == 0)


def test_bad_input_is_refused(problem):
    coarse, y, mask, _ = problem
    with pytest.raises(ValueError, match=r"NaN/inf entries outside the mask.*finite_mask"):
        dic_data(coarse, y)
    with pytest.raises(ValueError, match=r"shape \(76, 2\) but the scene's grid has 77 points"):
        dic_data(coarse, y[:-1], mask[:-1])
    with pytest.raises(ValueError, match="mask must be boolean"):
        dic_data(coarse, y, mask.astype(float))
    nominal = {"K": 2500.0, "G": 1200.0}
    with pytest.raises(ValueError, match=r"prior of G .*negative moduli.*LogNormal"):
        elastic_dic(coarse, nominal, 0.1, priors={"G": dist.Normal(1200.0, 300.0)})
    with pytest.raises(ValueError, match=r"prior of delta has support \[0.5, 3\].*h = 1.*ScaledBeta\(1, 3\)"):
        elastic_dic(coarse, nominal, 0.1, priors={"delta": ScaledBeta(0.5, 3.0)})
    with pytest.raises(ValueError, match=r"no such parameter\(s\) \['nu'\]"):
        elastic_dic(coarse, nominal, 0.1, priors={"nu": dist.Uniform(0.0, 0.5)})
    with pytest.raises(ValueError, match="nominal K must be finite and positive"):
        elastic_dic(coarse, {"K": -1.0, "G": 1200.0}, 0.1)
    with pytest.raises(ValueError, match="needs a scene observed through bp.GridObservation"):
        elastic_dic(scene(1.0, 3.0, bp.Observation), nominal, 0.1)


def test_a_discrepancy_term_enters_the_masked_likelihood(problem):
    """A term with mean m and no covariance shifts the data by m: the log density of y with the
    term equals that of y - m without it, over the kept entries only (the band must not count)."""
    coarse, y, mask, sigma = problem
    data = dic_data(coarse, y, mask)
    m = torch.linspace(-1.0, 1.0, data["y"].numel()).reshape(data["y"].shape) * sigma
    n = m.numel()
    term = bp.Discrepancy(m, torch.zeros(n, 1), torch.zeros(n), rms=1.0, explained=0.0, num_draws=1)
    at = {"K": torch.tensor(2900.0), "G": torch.tensor(1350.0), "delta": torch.tensor(2.6),
          "sigma": torch.tensor(sigma)}

    def log_likelihood(discrepancy, obs):
        model = elastic_dic(coarse, {"K": 2500.0, "G": 1200.0}, 0.05 * float(np.nanmax(np.abs(y))),
                            {"delta": ScaledBeta(2.3, 2.9)}, discrepancy)
        trace = pyro.poutine.trace(pyro.poutine.condition(model, data=at)).get_trace(obs, data["mask"])
        trace.compute_log_prob()
        return float(trace.nodes["y"]["log_prob_sum"])

    assert log_likelihood(term, data["y"]) == pytest.approx(log_likelihood(None, data["y"] - m), rel=1e-10)
    assert log_likelihood(term, data["y"]) != pytest.approx(log_likelihood(None, data["y"]), rel=1e-3)
