"""bayespd/plot.py: the crack-ensemble figures drawn from a known aggregate, written to PNG
and read back (signature, pixel size from the figure size and dpi, the axes and artists
that carry the data)."""
import struct

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import bayespd as bp  # noqa: E402
from bayespd import plot  # noqa: E402
from bayespd.ensemble.scene import FractureScene  # noqa: E402
from bayespd.ensemble.stats import aggregate  # noqa: E402

N = 7  # realisations per ensemble


def build(params):  # a picklable placeholder: aggregate never runs the scene
    raise NotImplementedError


@pytest.fixture(scope="module")
def ds():
    """A 4 x 4 body; realisation k of each ensemble has a straight crack at height 1 + c_k
    across it, phi rising along x, and failure load factor 1 + k / 10 (posterior) or
    2 + k / 10 (mean); one mean realisation never fails (NaN)."""
    x = bp.grid_2d(4.0, 4.0, 1.0).x
    scene = FractureScene(build, ("K",), [1.0, 2.0], 1.0, x, origin=(0.0, 1.0),
                          observed_path=np.array([[0.0, 1.2], [4.0, 1.2]]))
    rng = np.random.default_rng(0)
    results = []
    for kind, base in (("posterior", 1.0), ("mean", 2.0)):
        for k in range(N):
            c = 0.2 * rng.standard_normal()
            fail = np.nan if (kind == "mean" and k == 0) else base + k / 10
            res = {"t": np.arange(2.0), "load_factor": np.array([1.0, 2.0]), "reaction": np.ones((2, 2)),
                   "broken": np.array([0, 3]), "crack_length": np.array([0.0, 4.0]),
                   "phi": np.clip(x[:, 0] / 4 + 0.1 * rng.standard_normal(len(x)), 0, 1),
                   "path": np.array([[0.0, 1 + c], [2.0, 1 + c], [4.0, 1 + c]]),
                   "peak_load": 1.0, "peak_load_factor": 2.0, "failure_load_factor": fail,
                   "final_crack_length": 4.0, "first_failure_time": 1.0}
            results.append((kind, k, res, {"K": 1.0}, k, k))
    return aggregate(results, scene, seed=0)


def png_size(path):
    """(width, height) from a PNG's signature and IHDR chunk."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def test_ensemble_figures_are_three_pngs_of_the_stated_size(ds, tmp_path):
    """Three non-empty PNG files at figsize x 110 dpi: 6 x 5, 7 x 4 and 6 x 4 inches; no
    temporary left behind."""
    paths = plot.ensemble_figures(ds, tmp_path)
    assert [p.name for p in paths] == ["damage_probability.png", "crack_paths.png", "failure_load.png"]
    sizes = {p.name: png_size(p) for p in paths}
    assert sizes == {"damage_probability.png": (660, 550), "crack_paths.png": (770, 440),
                     "failure_load.png": (660, 440)}
    assert all(p.stat().st_size > 1000 for p in paths)
    assert sorted(q.name for q in tmp_path.iterdir()) == sorted(p.name for p in paths)
    image = plt.imread(paths[0])
    assert image.shape[:2] == (550, 660) and image.std() > 0.05  # not a blank canvas


def test_damage_probability_maps_the_probability_with_a_colour_bar(ds):
    """One tripcolor over the particles with the posterior probabilities as its values
    (vmin 0, vmax 1), a colour bar (two axes in the figure), the observed crack as a line."""
    ax = plot.damage_probability(ds)
    try:
        assert len(ax.figure.axes) == 2
        (mesh,) = ax.collections
        np.testing.assert_array_equal(mesh.get_array(), ds["probability"].sel(kind="posterior").values)
        assert mesh.get_clim() == (0, 1)
        (line,) = ax.lines
        np.testing.assert_array_equal(line.get_xydata(), ds["observed_path"].values)
        assert f"over {N} realisations (posterior)" in ax.get_title()
    finally:
        plt.close(ax.figure)


def test_path_overlay_draws_each_path_and_the_posterior_band(ds):
    """2 N paths and the observed one as lines (at most max_paths per ensemble); the band is
    one polygon whose lower and upper edges are the 5 % and 95 % offsets of the posterior
    paths (c_k here) across the line y = 1."""
    ax = plot.path_overlay(ds)
    try:
        assert len(ax.figure.axes) == 1 and len(ax.lines) == 2 * N + 1
        (band,) = ax.patches
        verts = band.get_xy()
        q = ds["path_quantiles"].sel(kind="posterior")
        lo, hi = 1 + q.sel(quantile=0.05).values, 1 + q.sel(quantile=0.95).values
        stations = ds["station"].values
        np.testing.assert_allclose(verts[: len(stations)], np.c_[stations, lo], atol=1e-12)
        np.testing.assert_allclose(verts[len(stations): 2 * len(stations)], np.c_[stations, hi][::-1], atol=1e-12)
        c = ds["path"].values[ds["ensemble"].values == "posterior", 0, 1]
        np.testing.assert_allclose(lo[0], np.quantile(c, 0.05), atol=1e-12)
    finally:
        plt.close(ax.figure)
    ax = plot.path_overlay(ds, max_paths=2)
    assert len(ax.lines) == 2 * 2 + 1
    plt.close(ax.figure)


def test_failure_histogram_counts_the_finite_outcomes(ds):
    """The bars of each ensemble count its finite failure loads (N posterior, N - 1 mean);
    two dashed lines per ensemble at its 5 % and 95 % quantiles."""
    ax = plot.failure_load_histogram(ds)
    try:
        heights = {}
        for bars in ax.containers:
            kind = bars.patches[0].get_label().split(":")[0]  # hist labels the first bar
            heights[kind] = sum(b.get_height() for b in bars)
        assert heights == {"posterior": N, "mean": N - 1}
        x = sorted(line.get_xdata()[0] for line in ax.lines)
        post = ds["failure_load_factor_quantiles"].sel(kind="posterior", quantile=[0.05, 0.95]).values
        mean = ds["failure_load_factor_quantiles"].sel(kind="mean", quantile=[0.05, 0.95]).values
        np.testing.assert_allclose(x, sorted([*post, *mean]), rtol=1e-15)
    finally:
        plt.close(ax.figure)


def test_drawing_on_a_given_axes_returns_it(ds):
    fig, axes = plt.subplots(1, 3)
    try:
        for ax, draw in zip(axes, (plot.damage_probability, plot.path_overlay, plot.failure_load_histogram)):
            assert draw(ds, ax=ax) is ax
        assert len(fig.axes) == 4  # three panels and one colour bar
    finally:
        plt.close(fig)
