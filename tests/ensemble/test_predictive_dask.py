"""Scale-out of crack ensembles: a local process pool and a Dask LocalCluster of 2 worker
processes (by Client and by scheduler address) give the in-process result bit for bit,
because each realisation's inputs depend only on (seed, i) and each runs on one thread."""
import numpy as np
import pytest
import xarray as xr

from bayespd.infer.datatree import build_tree
from bayespd.scenes.notched_plate import notched_plate
from bayespd.ensemble.stats import TIMES
from bayespd.ensemble.predictive import ensemble

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    rng = np.random.default_rng(3)
    tree = build_tree({"posterior": {"K": 3000 * (1 + 0.05 * rng.standard_normal((1, 20))),
                                     "s0": 0.0094 * (1 + 0.05 * rng.standard_normal((1, 20)))}})
    scene = notched_plate(side=12.0, h=1.0, steps=12, sigma=100.0)
    serial = ensemble(tree, scene, 4, n_mean=2, store=tmp_path_factory.mktemp("serial"), workers=1,
                      progress=False)
    return tree, scene, serial.drop_vars(TIMES)


def test_process_pool_matches_the_serial_run(setup, tmp_path):
    tree, scene, serial = setup
    pooled = ensemble(tree, scene, 4, n_mean=2, store=tmp_path, workers=2, progress=False)
    xr.testing.assert_identical(pooled.drop_vars(TIMES), serial)


def test_dask_cluster_matches_the_serial_run_and_resumes(setup, tmp_path):
    """Client and address give identical results; a second call on a full store runs nothing
    (every realisation file keeps its mtime) and one deleted file is re-run on the cluster."""
    tree, scene, serial = setup
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        by_client = ensemble(tree, scene, 4, n_mean=2, store=tmp_path / "a", scheduler=client, progress=False)
        xr.testing.assert_identical(by_client.drop_vars(TIMES), serial)
        assert {w["nthreads"] for w in client.scheduler_info()["workers"].values()} == {1}
        files = {p: p.stat().st_mtime_ns for p in (tmp_path / "a").glob("*.npz")}
        (tmp_path / "a" / "posterior-00002.npz").unlink()
        again = ensemble(tree, scene, 4, n_mean=2, store=tmp_path / "a", scheduler=cluster.scheduler_address,
                         progress=False)
        xr.testing.assert_identical(again.drop_vars(TIMES), serial)
        changed = [p.name for p, t in files.items() if p.stat().st_mtime_ns != t]
        assert changed == ["posterior-00002.npz"]
