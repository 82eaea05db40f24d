"""bayespd/ensemble/store.py: realisation files written atomically and read back bit for bit,
failed realisations kept, plans that differ refused, the aggregate's NetCDF round trip."""
import json

import numpy as np
import pytest
import xarray as xr

from bayespd.ensemble.store import EnsembleStore, PlanMismatchError

PLAN = {"seed": 0, "n_posterior": 4, "n_mean": 2, "params": ["K", "s0"]}


def test_realisations_round_trip_bit_for_bit(tmp_path):
    """float64 / int64 / string arrays written as .npz come back equal, dtypes included; a
    failed realisation is a .err.json read back as its dict; done() sees both."""
    store = EnsembleStore(tmp_path, PLAN)
    rng = np.random.default_rng(0)
    result = {"phi": rng.random(50), "path": rng.random((7, 2)), "broken": np.arange(5, dtype=np.int64),
              "peak_load": np.float64(np.pi), "device": np.str_("cpu")}
    assert not store.done("posterior", 17)
    store.write("posterior", 17, result)
    store.write("mean", 3, {"error": "NumericalInstabilityError: reduce dt"})
    assert store.done("posterior", 17) and store.done("mean", 3) and not store.done("mean", 17)
    back = store.read("posterior", 17)
    assert set(back) == set(result)
    for k, v in result.items():
        assert back[k].dtype == np.asarray(v).dtype and np.array_equal(back[k], v)
    assert store.read("mean", 3) == {"error": "NumericalInstabilityError: reduce dt"}
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["mean-00003.err.json", "plan.json", "posterior-00017.npz"]
    assert json.loads((tmp_path / "plan.json").read_text()) == PLAN


def test_reopening_keeps_the_plan_and_removes_stale_temporaries(tmp_path):
    """The same plan (in any key order) reopens the store and what it holds; a *.tmp left by
    a crash mid-write is deleted; a different plan is refused, naming the keys that differ."""
    EnsembleStore(tmp_path, PLAN).write("posterior", 0, {"phi": np.ones(3)})
    (tmp_path / "posterior-00001.npz.x.tmp").write_bytes(b"half a file")
    store = EnsembleStore(tmp_path, dict(reversed(list(PLAN.items()))))
    assert store.done("posterior", 0) and not list(tmp_path.glob("*.tmp"))
    with pytest.raises(PlanMismatchError, match=r"another plan \(differs in \['n_mean', 'seed'\]\).*new directory"):
        EnsembleStore(tmp_path, {**PLAN, "seed": 1, "n_mean": 3})


def test_dataset_round_trips_through_netcdf(tmp_path):
    """save_dataset writes NetCDF (h5netcdf) that opens identical: values, coordinates,
    string labels and attributes."""
    ds = xr.Dataset({"phi": (("realisation", "particle"), np.random.default_rng(1).random((3, 4))),
                     "draw": ("realisation", np.array([4, -1, 7], dtype=np.int64))},
                    coords={"ensemble": ("realisation", np.array(["posterior", "mean", "posterior"])),
                            "quantile": [0.05, 0.5, 0.95]},
                    attrs={"threshold": 0.4, "failed_realisations": "", "origin": [0.0, 1.0]})
    store = EnsembleStore(tmp_path, PLAN)
    store.save_dataset(ds)
    with xr.open_dataset(tmp_path / "ensemble.nc", engine="h5netcdf") as back:
        xr.testing.assert_identical(back.load(), ds)
    assert not list(tmp_path.glob("*.tmp"))


def test_damaged_files_are_named(tmp_path):
    store = EnsembleStore(tmp_path, PLAN)
    store.write("posterior", 2, {"phi": np.ones(1000)})
    path = tmp_path / "posterior-00002.npz"
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError, match=r"cannot read .*posterior-00002.npz as a stored realisation .*delete it"):
        store.read("posterior", 2)
    (tmp_path / "plan.json").write_text('{"seed": 0, "n_po')
    with pytest.raises(ValueError, match=r"cannot read .*plan.json as the store's plan .*delete the store"):
        EnsembleStore(tmp_path, PLAN)


def test_a_store_path_that_is_a_file_is_named(tmp_path):
    (tmp_path / "store").write_text("x")
    with pytest.raises(ValueError, match="the ensemble store .*store is a file, not a directory"):
        EnsembleStore(tmp_path / "store", {"n": 1})
