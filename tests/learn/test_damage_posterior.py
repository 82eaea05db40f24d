"""The damage posterior (bayespd.scenes.md_fracture): its zoomed s0 grid, and its bands carried to
another scene; the displacement error's diagnosis."""
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

from bayespd.scenes.md_fracture import _elsewhere, _Prediction, _zoom, displacement_diagnosis

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


@pytest.mark.parametrize("relative", [False, True])
def test_bands_carried_to_another_scene_hold_their_level(relative):
    """Another scene whose MD data are one run plus independent N(0, sd^2) errors, sd = 0.3 A (or
    0.2 times each frame's rms displacement), and 200 draws of that run with that level: a value
    lies inside the 5-95 % quantiles of 200 draws with probability 190.05 / 201 - 10.95 / 201 =
    0.891 (order statistics), a node-frame (both components) 0.891^2 = 0.794; over 2,000 node-frames
    the share is within 4 binomial sds (0.036) of it. Twice the level would give 0.998."""
    rng = np.random.default_rng(3)
    frames, nodes = 21, 100
    t = np.linspace(0.0, 2.0, frames)
    u_run = t[:, None, None] * rng.normal(1.0, 0.3, (1, nodes, 2))
    rms = np.sqrt((u_run**2).mean((1, 2)))
    level = 0.2 if relative else 0.3
    sd = level * rms[:, None, None] if relative else level
    bonds = SimpleNamespace(i=np.arange(nodes - 1), j=np.arange(1, nodes))  # intact throughout: no crack
    run = SimpleNamespace(u=u_run, intact=np.ones((frames, nodes - 1)))
    other = SimpleNamespace(fixed=np.zeros(nodes, bool), time=t, u=u_run + sd * rng.standard_normal(u_run.shape),
                            tip=np.full(frames, np.nan), runs=lambda s0s, widths: [run for _ in s0s],
                            material=SimpleNamespace(particles=SimpleNamespace(x=u_run[1]), bonds=bonds))
    other.u[0] = 0.0  # frame 0 is the reference and is left out
    draws = 200
    fit = _Prediction(np.ones(1), np.zeros(draws, int), None, None, {}, np.full(draws, level), np.zeros(draws), relative)

    def carried():
        return _elsewhere(other, 1.0, (np.ones(1), np.ones(1)), {"model": fit}, 1.0, rng)["model"]
    assert abs(carried()["band90_node_frame_coverage"] - 0.891**2) < 0.036
    assert carried()["crack_initiation_ps"]["runs_without_crack"] == draws  # nor has MD: nothing to compare
    fit.level = 2 * fit.level
    assert carried()["band90_node_frame_coverage"] > 0.95


def test_the_displacement_diagnosis_separates_amplitude_and_place():
    """MD's field 1.5 times the run's: the factor is 1.5, the error 1/3 of MD's field beside the slit
    line and away from it, and nothing is left after the factor. MD's field the run's plus 0.2 A
    beside the line and 1.5 times it away: the error away is 1/3, the one beside it the 0.2 A."""
    rng = np.random.default_rng(4)
    frames, nodes = 5, 60
    x = np.column_stack([np.linspace(-30.0, 30.0, nodes), np.zeros(nodes)])
    band = np.abs(x[:, 0] - 0.5) <= 10.0
    u = np.concatenate([np.zeros((1, nodes, 2)), rng.normal(1.0, 0.3, (frames - 1, nodes, 2))])

    def diagnosis(u_md):
        sc = SimpleNamespace(fixed=np.zeros(nodes, bool), slit_x=0.5, params={"delta": 10.0}, u=u_md,
                             material=SimpleNamespace(particles=SimpleNamespace(x=x)))
        return displacement_diagnosis(sc, SimpleNamespace(u=u))
    out = diagnosis(1.5 * u)
    np.testing.assert_allclose(out["md_over_pd_factor"], 1.5, rtol=1e-14)
    for key in ("rel_error_near_slit_line", "rel_error_elsewhere"):
        np.testing.assert_allclose(out[key], 1 / 3, rtol=1e-12)
    np.testing.assert_allclose(out["rel_error_after_factor"], 0.0, atol=1e-14)
    assert len(out["md_over_pd_factor"]) == frames - 1
    u_md = np.where(band[None, :, None], u + 0.2, 1.5 * u)
    out = diagnosis(u_md)
    np.testing.assert_allclose(out["rel_error_elsewhere"], 1 / 3, rtol=1e-12)
    near = np.linalg.norm(np.full((band.sum(), 2), 0.2)) / np.linalg.norm(u_md[1:, band], axis=(1, 2))
    np.testing.assert_allclose(out["rel_error_near_slit_line"], near, rtol=1e-12)
