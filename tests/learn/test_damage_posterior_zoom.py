"""The damage posterior's zoomed s0 grid (bayespd.scenes.md_fracture._zoom)."""
import numpy as np
from scipy import stats

from bayespd.scenes.md_fracture import _zoom

S0 = np.exp(np.linspace(np.log(0.01), np.log(1.0), 61))


def weights(centre, sd, tail=0.0):
    """A log-normal marginal on the coarse grid, with ``tail`` of the mass spread evenly above it."""
    w = stats.norm.pdf(np.log(S0), np.log(centre), sd)
    w = (1 - tail) * w / w.sum() + tail * (S0 > 3 * centre) / (S0 > 3 * centre).sum()
    return w


def test_the_zoom_holds_every_model_but_the_mass_it_reports():
    models = {"sharp": weights(0.14, 0.02), "wide": weights(0.13, 0.15, tail=4e-4)}
    fine, lost = _zoom(S0, models)
    assert len(fine) == 61 and np.allclose(np.diff(np.log(fine)), np.diff(np.log(fine))[0])
    assert lost <= 1e-3
    for w in models.values():  # the mass outside the zoomed range is what it reports, at most
        assert w[(S0 < fine[0]) | (S0 > fine[-1])].sum() <= lost + 1e-15
    # a tail of 4e-4 far above the peak is left out rather than stretching the grid 7-fold
    assert fine[-1] < 0.3 and fine[0] > 0.05
    assert np.log(fine[-1] / fine[0]) / 60 < np.log(S0[1] / S0[0]) / 3  # 3x finer than the coarse step, even for the wide one
