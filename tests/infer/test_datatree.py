"""``bayespd.infer.datatree`` on small hand-built trees (no sampling): the layout and dims of
``build_tree``, the NetCDF round trip bit for bit, ``summary``'s columns against numpy and
its diagnostic warnings by the Vehtari et al. (2021) thresholds, the ``modes`` table and E, nu
intervals from K, G draws.
(The same functions on a real NUTS fit are checked in ``tests/infer/test_fit.py``.)"""
import json
import warnings

import numpy as np
import pytest
import xarray as xr

import bayespd as bp
from bayespd.infer import load, save, summary, to_inference_data, young_intervals
from bayespd.infer.datatree import build_tree, modes


def draws(chains=2, n=500, seed=0, shift=None):
    """iid N(0, 1) draws of a scalar ``a`` and a 3-vector ``b`` (chain, draw, ...)."""
    rng = np.random.default_rng(seed)
    a, b = rng.standard_normal((chains, n)), rng.standard_normal((chains, n, 3))
    if shift is not None:
        a[1] += shift
    return {"a": a, "b": b}


def small_tree(method="nuts", **kw):
    rng = np.random.default_rng(9)
    post = draws(**kw)
    c, n = post["a"].shape
    stats = {"diverging": np.zeros((c, n), bool), "tree_depth": np.full((c, n), 3, np.int64),
             "energy": rng.standard_normal((c, n)) + 10.0}
    groups = {"posterior": post, "sample_stats": stats,
              "log_likelihood": {"y": rng.standard_normal((c, n, 4))},
              "observed_data": {"y": np.arange(4.0), "mask": np.array([True, False, True, True])}}
    attrs = {"method": method, "wall_time_s": 1.25, "settings": json.dumps({"max_tree_depth": 10})}
    return build_tree(groups, attrs, dims={"b": ["component"], "y": ["point"]},
                      coords={"component": ["u", "v", "w"]})


def test_build_tree_names_dims_and_keeps_data_groups_without_sample_dims():
    tree = small_tree()
    assert set(tree.children) == {"posterior", "sample_stats", "log_likelihood", "observed_data"}
    assert tree["posterior"]["a"].dims == ("chain", "draw")
    assert tree["posterior"]["b"].dims == ("chain", "draw", "component")
    assert list(tree["posterior"]["component"].values) == ["u", "v", "w"]
    np.testing.assert_array_equal(tree["posterior"]["chain"].values, [0, 1])
    assert tree["log_likelihood"]["y"].dims == ("chain", "draw", "point")
    assert tree["observed_data"]["y"].dims == ("point",)
    assert tree["observed_data"]["mask"].dims == ("mask_dim_0",)  # no dims given: v_dim_i
    assert set(to_inference_data(tree).groups()) == set(tree.children)


def test_save_load_round_trip_is_bit_for_bit(tmp_path):
    tree = small_tree()
    path = tmp_path / "tree.nc"
    save(tree, path)
    save(tree, path)  # overwrites in place, atomically
    assert [p.name for p in tmp_path.iterdir()] == ["tree.nc"]
    loaded = load(path)
    path.unlink()  # read fully into memory
    xr.testing.assert_identical(loaded, tree)
    assert loaded.attrs == tree.attrs
    for group in tree.children:
        for name, var in tree[group].data_vars.items():
            assert loaded[group][name].dtype == var.dtype
            assert loaded[group][name].values.tobytes() == var.values.tobytes()


def test_summary_columns_are_the_draws_moments():
    """mean and sd over all chains and draws (numpy, ddof = 1 as ArviZ), the 90 % HDI, and
    bulk ESS of iid draws near the number of draws (1000: within 30 %)."""
    tree = small_tree(method="svi")
    df = summary(tree, var_names=["a", "b"])
    assert list(df.index) == ["a", "b[u]", "b[v]", "b[w]"]
    assert {"mean", "sd", "hdi_5%", "hdi_95%", "mcse_mean", "ess_bulk", "ess_tail", "r_hat"} <= set(df.columns)
    a = tree["posterior"]["a"].values
    assert df.loc["a", "mean"] == pytest.approx(a.mean(), abs=0.005)  # ArviZ rounds to 2 digits
    assert df.loc["a", "sd"] == pytest.approx(a.std(ddof=1), abs=0.005)
    assert df.loc["a", "hdi_5%"] < np.quantile(a, 0.1) and df.loc["a", "hdi_95%"] > np.quantile(a, 0.9)
    assert 700 < df.loc["a", "ess_bulk"] < 1300


def test_summary_warns_for_mcmc_only_naming_the_failed_diagnostic():
    """Chains 3 sd apart: r_hat far above 1.01 for a NUTS fit; the same draws from SVI are
    independent and get no warning; iid chains that agree get none either."""
    with pytest.warns(UserWarning) as record:  # two chains 3 sd apart also have a low ESS
        summary(small_tree(shift=3.0), var_names=["a"])
    assert "r_hat > 1.01 for a: the chains have not mixed" in str(record[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        summary(small_tree(method="svi", shift=3.0), var_names=["a"])
        summary(small_tree(), var_names=["a", "b"])


def test_summary_warns_on_divergences_and_maximum_tree_depth():
    tree = small_tree()
    st = tree["sample_stats"].to_dataset()
    st["diverging"][0, 4] = st["diverging"][1, 7] = True
    st["tree_depth"][1, :5] = 10
    tree["sample_stats"] = st
    with pytest.warns(UserWarning) as record:
        summary(tree, var_names=["a"])
    messages = " ".join(str(w.message) for w in record)
    assert "2 divergent transitions" in messages
    assert "5 draws hit max_tree_depth 10" in messages


def test_modes_table_and_mixed_modes():
    found = [{"potential": 1.0, "values": {"K": 2.0, "field": [1.0, 2.0]}},
             {"potential": 4.5, "values": {"K": 3.0, "field": [0.0, 0.0]}}]
    tree = build_tree({"posterior": draws()}, {"map_modes": json.dumps(found)})
    table = modes(tree)
    assert list(table.columns) == ["potential", "K"]  # scalar parameters only
    np.testing.assert_array_equal(table["K"], [2.0, 3.0])
    assert modes(tree, mixed=True) is None  # found but not mixed
    weighted = [dict(m, weight=w) for m, w in zip(found, (0.8, 0.2))]
    tree = build_tree({"posterior": draws()}, {"mode_weights": json.dumps(weighted), "method": "svi"})
    np.testing.assert_array_equal(modes(tree, mixed=True)["weight"], [0.8, 0.2])
    assert summary(tree, var_names=["a"]).attrs["modes"].shape == (2, 3)
    assert modes(build_tree({"posterior": draws()})) is None


def test_load_names_a_truncated_or_foreign_file(tmp_path):
    path = tmp_path / "fit.nc"
    save(small_tree(), path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"cannot read .*fit.nc as a NetCDF result tree \(.*\): it is truncated"):
        load(path)
    path.write_bytes(b"not a netcdf file\n" * 10)
    with pytest.raises(ValueError, match=r"cannot read .*fit.nc as a NetCDF result tree"):
        load(path)
    with pytest.raises(FileNotFoundError, match="no result file .*missing.nc: check the path"):
        load(tmp_path / "missing.nc")


def test_young_intervals_of_known_draws():
    """E uniform on a grid of 1001 values in [1000, 2000] at nu = 0.3: mean 1500, sd that of the
    grid, linear-interpolated 5 % / 95 % quantiles 1050 / 1950 (25 % / 75 %: 1250 / 1750 for
    level 0.5), nu exactly 0.3; a posterior without K, G or a level outside (0, 1) is refused."""
    E = np.linspace(1000.0, 2000.0, 1001)
    K, G = bp.moduli_from_young(E, 0.3)
    tree = {"posterior": xr.Dataset({"K": (("chain", "draw"), np.asarray(K)[None]),
                                     "G": (("chain", "draw"), np.asarray(G)[None])})}
    out = young_intervals(tree)
    assert out["E"]["mean"] == pytest.approx(1500.0, rel=1e-12)
    assert out["E"]["sd"] == pytest.approx(float(np.std(E)), rel=1e-12)
    assert out["E"]["interval_90"] == pytest.approx([1050.0, 1950.0], rel=1e-12)
    assert out["nu"]["interval_90"] == pytest.approx([0.3, 0.3], rel=1e-12)
    assert young_intervals(tree, 0.5)["E"]["interval_50"] == pytest.approx([1250.0, 1750.0], rel=1e-12)
    with pytest.raises(ValueError, match="no \\['G'\\].*moduli K and G"):
        young_intervals({"posterior": tree["posterior"][["K"]]})
    with pytest.raises(ValueError, match="level must lie in \\(0, 1\\)"):
        young_intervals(tree, 90)
