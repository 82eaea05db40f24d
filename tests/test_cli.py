"""The ``bayespd`` command: exit codes (0 done, 2 usage, 1 failure), messages that name the
fix, and calibrate -> predict -> summary on the demo's tiny inputs."""
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
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


TINY_MODEL = '''
import math, os, time

import pyro
import pyro.distributions as dist
import torch

import bayespd as bp

PAUSE = float(os.environ.get("TINY_PAUSE", "0"))  # seconds per sampler run: time to kill it


def scene():
    p = bp.grid_2d(6.0, 3.0, 1.0)
    return bp.Scene(bp.BondBased(p, bp.find_bonds(p, 2.0)), [bp.Dirichlet.layer(p, "left", 2.0)],
                    [bp.Load(p.layer("right", 1.0), (10.0, 0.0))], bp.Observation(p, p.x[p.x[:, 0] > 2.0]))


def model(scene):
    def m(y=None):
        if PAUSE and torch.is_grad_enabled():
            time.sleep(PAUSE)
        K = pyro.sample("K", dist.LogNormal(math.log(2500.0), 0.5))
        mean = scene.observe(scene.solve({"K": K, "delta": 2.0}))
        with pyro.plate("point", mean.shape[0], dim=-2), pyro.plate("component", 2, dim=-1):
            pyro.sample("y", dist.Normal(mean, 1e-3), obs=y)
    return m
'''


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A 6 x 3 bond-based plate, K to calibrate from 24 noisy displacements (K = 3000)."""
    folder = tmp_path_factory.mktemp("tiny")
    (folder / "model.py").write_text(TINY_MODEL)
    module = cli.load_module(folder / "model.py", "tiny_model")
    scene = module.scene()
    u = scene.observe(scene.solve({"K": torch.tensor(3000.0), "delta": 2.0}))
    np.savez(folder / "data.npz", y=(u + 1e-3 * torch.randn(u.shape, generator=torch.Generator().manual_seed(0))).numpy())
    return folder


def nuts_args(tiny, out, *extra):
    return ["calibrate", str(tiny / "model.py"), "--data", str(tiny / "data.npz"), "--method", "nuts",
            "--out", str(out), "--warmup", "30", "--chains", "1", "--seed", "3", "--quiet", *extra]


def posterior_of(out):
    tree = load(out / "posterior.nc")
    return tree["posterior"].to_dataset(), tree["sample_stats"].to_dataset()


def test_calibrate_checkpoint_reloads_the_finished_chains(tiny, tmp_path, monkeypatch):
    """The second run with the same --checkpoint samples nothing and writes the same draws."""
    assert main(nuts_args(tiny, tmp_path / "a", "--samples", "20", "--checkpoint", str(tmp_path / "ck"))) == 0
    assert (tmp_path / "ck" / "chain0.pt").exists()
    from bayespd.infer import mcmc

    monkeypatch.setattr(mcmc, "_kernel", None)  # a run that samples would call it
    assert main(nuts_args(tiny, tmp_path / "b", "--samples", "20", "--checkpoint", str(tmp_path / "ck"))) == 0
    for a, b in zip(posterior_of(tmp_path / "a"), posterior_of(tmp_path / "b")):
        xr.testing.assert_identical(a, b)


@pytest.mark.slow
def test_a_killed_calibration_resumes_from_its_checkpoint(tiny, tmp_path):
    """`bayespd calibrate --checkpoint` SIGKILLed part-way through its draws; the same command
    again ends with the draws of an uninterrupted run, bit for bit."""
    assert main(nuts_args(tiny, tmp_path / "whole", "--samples", "60")) == 0
    command = [sys.executable, "-m", "bayespd.cli", *nuts_args(tiny, tmp_path / "resumed", "--samples", "60",
                                                              "--checkpoint", str(tmp_path / "ck"),
                                                              "--checkpoint-every", "5")]
    env = dict(os.environ, TINY_PAUSE="0.02", PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    run = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    saved = tmp_path / "ck" / "chain0.pt"
    end = time.monotonic() + 120
    while not (saved.exists() and len(torch.load(saved, weights_only=True)["draws"].get("K", [])) >= 10):
        assert time.monotonic() < end and run.poll() is None, "no draws saved"
        time.sleep(0.05)
    run.kill()
    run.wait(10)
    assert len(torch.load(saved, weights_only=True)["draws"]["K"]) < 60  # killed part-way
    done = subprocess.run(command, env=dict(env, TINY_PAUSE="0"), capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    for a, b in zip(posterior_of(tmp_path / "whole"), posterior_of(tmp_path / "resumed")):
        xr.testing.assert_identical(a, b)


BAD_MODEL = [
    ("def scene(:\n    pass\n", "line 1: invalid syntax: fix the Python syntax there"),
    ("def scene(n):\n    pass\n", "scene(n) in {path} cannot be called as scene() (missing a required argument: "
                                 "'n'): define it as scene(), returning a bayespd.Scene"),
    ("raise RuntimeError('boom')\n", "running {path} raised RuntimeError: boom: fix that file"),
]


@pytest.mark.parametrize("text, message", BAD_MODEL)
def test_a_broken_model_file_is_named_with_the_fix(tiny, tmp_path, capsys, text, message):
    path = tmp_path / "model.py"
    path.write_text(text)
    code = main(["calibrate", str(path), "--data", str(tiny / "data.npz"), "--method", "svi", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and message.format(path=path) in err and str(path) in err


def test_a_model_of_the_wrong_signature_is_refused(tiny, tmp_path, capsys):
    path = tmp_path / "model.py"
    path.write_text(TINY_MODEL.replace("def model(scene):", "def model():"))
    code = main(["calibrate", str(path), "--data", str(tiny / "data.npz"), "--method", "svi", "--out", str(tmp_path)])
    assert code == 2 and "model() in" in capsys.readouterr().err


def _bad_data(folder):
    y = np.zeros((12, 2))
    np.savez(folder / "strings.npz", y=y, label=np.array(["a", "b"]))
    np.savez(folder / "extra.npz", y=y, noise=np.ones(3))
    np.savez(folder / "whole.npz", y=y)
    (folder / "truncated.npz").write_bytes((folder / "whole.npz").read_bytes()[:200])
    (folder / "text.npz").write_text("y = 1, 2, 3\n")
    return {
        "strings": "array 'label' of {path} holds <U1 values, not numbers or booleans: save it as a numeric",
        "extra": "{path} holds ['noise'], which the model does not take (it takes ['y']): drop them",
        "truncated": "{path} is not a readable .npz file of numeric arrays (",
        "text": "{path} is not a readable .npz file of numeric arrays (ValueError: ",
    }


def test_bad_data_files_get_one_line_naming_the_file_and_the_fix(tiny, tmp_path, capsys):
    for name, message in _bad_data(tmp_path).items():
        path = tmp_path / f"{name}.npz"
        code = main(["calibrate", str(tiny / "model.py"), "--data", str(path), "--method", "nuts", "--out",
                     str(tmp_path / "out"), "--quiet"])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1 and message.format(path=path) in err, err


def test_counts_out_of_range_are_refused(tiny, capsys):
    for option, value, allowed in (("--warmup", "-1", 0), ("--samples", "0", 1), ("--chains", "0", 1),
                                   ("--checkpoint-every", "0", 1), ("--svi-steps", "x", 1)):
        with pytest.raises(SystemExit) as e:
            main(nuts_args(tiny, "out", option, value))
        assert e.value.code == 2
        assert f"argument {option}: must be an integer >= {allowed}, not '{value}'" in capsys.readouterr().err


def test_checkpoint_is_refused_for_a_method_without_chains(tiny, tmp_path, capsys):
    code = main(["calibrate", str(tiny / "model.py"), "--data", str(tiny / "data.npz"), "--method", "svi",
                 "--out", str(tmp_path), "--checkpoint", str(tmp_path / "ck")])
    assert code == 2 and "--checkpoint saves NUTS chains: use it with --method nuts, not svi" in capsys.readouterr().err
