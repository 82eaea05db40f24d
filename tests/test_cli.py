"""The ``bayespd`` command: exit codes (0 done, 2 usage, 1 failure), messages that name the
fix, and calibrate -> predict -> summary on the demo's tiny inputs."""
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from bayespd import cli
from bayespd.cli import main
from bayespd.ensemble.scene import realise
from bayespd.ensemble.predictive import posterior_draws, realisation_inputs
from bayespd.infer import load
from bayespd.infer.datatree import build_tree, save
from bayespd.ensemble.demo_inputs import write_inputs


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return write_inputs(tmp_path_factory.mktemp("inputs"))


@pytest.fixture(scope="module")
def laplace_dir(inputs, tmp_path_factory):
    out = tmp_path_factory.mktemp("laplace")
    code = main(["calibrate", str(inputs["model"]), "--data", str(inputs["data"]), "--method", "laplace",
                 "--out", str(out), "--samples", "200", "--quiet"])
    assert code == 0
    return out


def test_help_and_usage_errors(capsys, inputs, tmp_path):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0 and "fracture_scene()" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main(["calibrate", str(inputs["model"]), "--data", str(inputs["data"]), "--method", "mcmc", "--out", "x"])
    assert e.value.code == 2 and "invalid choice: 'mcmc'" in capsys.readouterr().err
    code = main(["calibrate", str(tmp_path / "nope.py"), "--data", str(inputs["data"]), "--method", "svi",
                 "--out", str(tmp_path)])
    assert code == 2 and "nope.py does not exist: check the path" in capsys.readouterr().err
    bare = tmp_path / "bare.py"
    bare.write_text(Path(inputs["model"]).read_text().replace("def model(scene):", "def other(scene):"))
    code = main(["calibrate", str(bare), "--data", str(inputs["data"]), "--method", "svi", "--out", str(tmp_path)])
    assert code == 2 and "defines no function model(scene)" in capsys.readouterr().err
    np.savez(tmp_path / "noy.npz", u=np.zeros(3))
    code = main(["calibrate", str(inputs["model"]), "--data", str(tmp_path / "noy.npz"), "--method", "svi",
                 "--out", str(tmp_path)])
    assert code == 2 and "no array 'y'" in capsys.readouterr().err
    code = main(["summary", str(tmp_path)])
    assert code == 2 and "neither posterior.nc" in capsys.readouterr().err


def test_tikhonov_agrees_with_the_laplace_posterior(inputs, laplace_dir, tmp_path, capsys):
    """Least squares (tikhonov, psi = 0) and the Laplace MAP differ only by the prior's pull,
    (posterior var / prior var) x log distance ~ 1e-5 relative here; the Laplace draws' mean
    is within 4 sd / sqrt(200) of its MAP. The data come from a grid twice as fine: K is
    below the truth 3000 by the discretisation bias (a few %), far more than its sd."""
    assert main(["calibrate", str(inputs["model"]), "--data", str(inputs["data"]), "--method", "tikhonov",
                 "--out", str(tmp_path)]) == 0
    k_tik = float(load(tmp_path / "posterior.nc")["posterior"]["K"].values.squeeze())
    k = load(laplace_dir / "posterior.nc")["posterior"]["K"].values.reshape(-1)
    assert abs(k_tik - k.mean()) < 4 * k.std() / np.sqrt(len(k)) + 1e-4 * k_tik
    assert 0.9 < k_tik / 3000 < 1.0 and k.std() < 0.01 * k_tik
    assert "K" in capsys.readouterr().out


def test_predict_and_summary(inputs, laplace_dir, capsys):
    """An ensemble at draws of the Laplace posterior: each realisation's K is one of the
    posterior's draws (the mean ensemble's the posterior mean), figures and the NetCDF file
    are written, summary prints the counts; a second call runs nothing new."""
    args = ["predict", str(laplace_dir), "--scene", str(inputs["scene"]), "--n", "3", "--n-mean", "2",
            "--workers", "1", "--quiet"]
    assert main(args) == 0
    with xr.open_dataset(laplace_dir / "ensemble" / "ensemble.nc", engine="h5netcdf") as ds:
        post = load(laplace_dir / "posterior.nc")["posterior"]["K"].values.reshape(-1)
        k = ds["param_K"].values
        assert set(k[ds["ensemble"].values == "posterior"]) <= set(post)
        assert np.allclose(k[ds["ensemble"].values == "mean"], post.mean(), rtol=1e-14)
    for name in ("damage_probability", "crack_paths", "failure_load"):
        assert (laplace_dir / "ensemble" / f"{name}.png").stat().st_size > 10_000
    capsys.readouterr()
    assert main(["summary", str(laplace_dir)]) == 0
    out = capsys.readouterr().out
    assert "3 posterior + 2 mean-parameter realisations, 0 failed" in out and "failure_load_factor" in out


OWN_SCENE = (
    "import dataclasses\nfrom functools import partial\n"
    "from bayespd.scenes.notched_plate import notched_plate, plate_driver\n\n"
    "def build(params, side):\n    return plate_driver(params, side=side, h=1.0, m=3, sigma=100.0, relax=1e4, dt=1.0)\n\n"
    "def fracture_scene():\n"
    "    return dataclasses.replace(notched_plate(side=10.0, steps=10, sigma=100.0), build=partial(build, side=10.0))\n")


def _predict_own_scene(laplace_dir, tmp_path, workers):
    scene = tmp_path / "own.py"
    scene.write_text(OWN_SCENE)
    target = tmp_path / f"w{workers}"
    target.mkdir()
    (target / "posterior.nc").write_bytes((laplace_dir / "posterior.nc").read_bytes())
    assert main(["predict", str(target), "--scene", str(scene), "--n", "2", "--n-mean", "0",
                 "--workers", str(workers), "--quiet"]) == 0
    return scene, np.load(target / "ensemble" / "posterior-00001.npz")["phi"]


def test_a_build_defined_in_the_scene_file_travels_by_path(laplace_dir, tmp_path, capsys):
    """A build function written in SCENE.py is wrapped so that it pickles by path: unpickled
    where the file was never loaded (cache and module dropped, as in a fresh worker) it
    loads the file and builds the same driver. A scene file without fracture_scene() and a
    posterior without the scene's parameters are refused with the fix named."""
    scene_path, phi = _predict_own_scene(laplace_dir, tmp_path, 1)
    scene = cli.load_scene(scene_path)
    blob = pickle.dumps(scene)
    cli._FILES.clear()
    sys.modules.pop(cli._module_name(scene_path))
    fresh = pickle.loads(blob)
    assert isinstance(fresh.build, cli.FileFunction) and fresh.build.path == str(scene_path.resolve())
    draws = posterior_draws(load(laplace_dir / "posterior.nc"), ("K", "s0"))
    params, _, b = realisation_inputs(draws, 0, 1)
    assert np.array_equal(realise(fresh, params, b)["phi"], phi) and phi.max() > 0.4
    (tmp_path / "empty.py").write_text("x = 1\n")
    assert main(["predict", str(tmp_path / "w1"), "--scene", str(tmp_path / "empty.py"), "--quiet"]) == 2
    assert "defines no function fracture_scene()" in capsys.readouterr().err
    (tmp_path / "c").mkdir()
    save(build_tree({"posterior": {"K": np.full((1, 2), 3000.0)}}), tmp_path / "c" / "posterior.nc")
    assert main(["predict", str(tmp_path / "c"), "--scene", str(scene_path), "--n", "2", "--quiet"]) == 1
    assert "no variable(s) ['s0']" in capsys.readouterr().err


@pytest.mark.slow
def test_a_build_defined_in_the_scene_file_runs_in_worker_processes(laplace_dir, tmp_path):
    """The same, through spawned worker processes (where the file is loaded by path)."""
    _, serial = _predict_own_scene(laplace_dir, tmp_path, 1)
    _, pooled = _predict_own_scene(laplace_dir, tmp_path, 2)
    assert np.array_equal(serial, pooled)


def test_the_entry_point_is_installed():
    """``bayespd`` is a console script of the package (pyproject [project.scripts])."""
    script = Path(sys.executable).with_name("bayespd")
    result = subprocess.run([str(script), "predict", "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "--scheduler ADDRESS" in result.stdout


@pytest.mark.slow
def test_demo_runs_end_to_end(tmp_path):
    result = subprocess.run([sys.executable, "-m", "bayespd.cli", "demo", "--out", str(tmp_path), "--quiet"],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert "8 posterior + 8 mean-parameter realisations, 0 failed" in result.stdout
