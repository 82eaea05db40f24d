"""bayespd/ensemble/demo_inputs.py: the demo's MODEL.py, SCENE.py and DATA.npz: files a user
would write, data from a twice finer grid (no inverse crime) with the stated noise."""
import importlib.util

import numpy as np
import pytest
import torch

from bayespd.ensemble import demo_inputs


def load(path, name):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    folder = tmp_path_factory.mktemp("demo")
    return folder, demo_inputs.write_inputs(folder, seed=3)


def test_files_are_written_and_are_the_module_texts(written):
    folder, paths = written
    assert set(paths) == {"model", "scene", "data"}
    assert sorted(p.name for p in folder.iterdir()) == ["data.npz", "model.py", "scene.py"]
    assert paths["model"].read_text() == demo_inputs.MODEL_PY
    assert paths["scene"].read_text() == demo_inputs.SCENE_PY
    model = load(paths["model"], "demo_model_under_test")
    assert callable(model.model) and model.init() == {"K": 2500.0} and model.fixed() == {"delta": 3.0}


def test_data_are_the_fine_grid_solution_plus_the_stated_noise(written):
    """y (points right of the clamp on the h = 1 grid, 17 x 10 of them) minus the h = 0.5
    solution at K_TRUE, divided by NOISE max|clean|, is standard normal: over its 340
    entries the sample mean lies within 4.5 / sqrt(340) of 0 and the sample variance within
    4.5 sqrt(2 / 340) of 1 (chi-square's sd; each fails by chance with probability 7e-6).
    The coarse model at K_TRUE is not the clean data (no inverse crime): their rms gap is
    well above rounding (measured 1.6 noise sd, the discretisation error at h = 1)."""
    _, paths = written
    y = np.load(paths["data"])["y"]
    model = load(paths["model"], "demo_model_for_data")
    coarse = model.scene()
    points = coarse.observation.points
    assert y.shape == (170, 2) and points.shape == (170, 2) and np.all(points[:, 0] > 3.0)
    fine = model.scene(h=0.5, points=points)
    with torch.no_grad():
        clean = fine.observe(fine.solve({"K": demo_inputs.K_TRUE, "delta": 3.0})).numpy()
        crime = coarse.observe(coarse.solve({"K": demo_inputs.K_TRUE, "delta": 3.0})).numpy()
    scale = demo_inputs.NOISE * np.abs(clean).max()
    z = (y - clean) / scale
    assert abs(z.mean()) < 4.5 / np.sqrt(z.size)
    assert abs(z.var() - 1) < 4.5 * np.sqrt(2 / z.size)
    gap = np.sqrt(np.mean((crime - clean) ** 2))
    assert gap > 0.1 * scale


def test_the_seed_fixes_the_noise(written, tmp_path):
    """The same seed writes the same bits; another seed other noise."""
    _, paths = written
    again = demo_inputs.write_inputs(tmp_path / "same", seed=3)
    assert np.array_equal(np.load(again["data"])["y"], np.load(paths["data"])["y"])
    other = demo_inputs.write_inputs(tmp_path / "other", seed=4)
    assert not np.array_equal(np.load(other["data"])["y"], np.load(paths["data"])["y"])
