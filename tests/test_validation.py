"""Bad input is refused early with a ValueError whose message names the fix."""
import numpy as np
import pytest
import torch

import bayespd as bp


@pytest.fixture(scope="module")
def plate():
    p = bp.grid_2d(10.0, 6.0, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 2.5))
    scene = bp.Scene(mat, [bp.Dirichlet.layer(p, "left", 2.5)], [bp.Load(p.layer("right", 1.0), (1.0, 0.0))])
    return p, mat, scene


@pytest.mark.parametrize("params, match", [
    ({"K": -1.0, "G": 1.0, "delta": 2.0}, "K must be positive"),
    ({"K": float("nan"), "G": 1.0, "delta": 2.0}, "K contains NaN"),
    ({"K": 1.0, "G": 0.0, "delta": 2.0}, "G must be positive"),
    ({"K": 1.0, "G": 1.0, "delta": 0.5}, "smaller than the grid spacing"),
    ({"K": 1.0, "G": 1.0, "delta": 3.0}, "larger delta_max"),
    ({"K": 1.0, "G": 1.0}, "missing \\['delta'\\]"),
])
def test_bad_params(plate, params, match):
    with pytest.raises(ValueError, match=match):
        plate[2].solve(params)


def test_per_particle_field_of_wrong_length(plate):
    with pytest.raises(ValueError, match="one value per particle"):
        plate[2].solve({"K": torch.ones(3), "G": 1.0, "delta": 2.0})


def test_thin_dirichlet_layer(plate):
    p, mat, _ = plate
    with pytest.warns(UserWarning, match="at least one horizon thick"):
        bp.Scene(mat, [bp.Dirichlet.layer(p, "left", 1.0)], [bp.Load(p.layer("right", 1.0), (1.0, 0.0))])


def test_observations_outside_body(plate):
    p = plate[0]
    with pytest.raises(ValueError, match="outside the body"):
        bp.Observation(p, [[5.0, 3.0], [50.0, 3.0]])
    holed = p.where(~p.box((4.2, 2.2), (5.8, 3.8)))  # a 2 x 2 hole
    with pytest.raises(ValueError, match="outside the body"):
        bp.Observation(holed, [[5.0, 3.0]])
    obs = bp.Observation(holed, [[3.25, 1.5]])  # inside the material: linear interpolation
    u = torch.as_tensor(holed.x) @ torch.tensor([[1.0, 2.0], [3.0, 4.0]]).T
    np.testing.assert_allclose(obs(u), [[3.25 + 2 * 1.5, 3 * 3.25 + 4 * 1.5]], rtol=1e-12)


def test_isolated_particle_has_empty_family():
    p = bp.grid_2d(6.0, 4.0, 1.0)
    lonely = bp.from_points(np.vstack([p.x, [[20.0, 20.0]]]), np.append(p.volume, 1.0))
    mat = bp.BondBased(lonely, bp.find_bonds(lonely, 2.0))
    with pytest.raises(ValueError, match="particle 24 .* empty family"):
        mat.stiffness({"K": 1.0, "delta": 2.0})


# the shared checks of bayespd.validate: name, value and fix in every message

def test_finite_names_the_bad_entry_and_the_fix():
    from bayespd.validate import finite
    with pytest.raises(ValueError, match=r"u contains NaN or inf \(1 of 3 entries, e.g. nan at index \(1,\)\): "
                                         r"give numbers"):
        finite("u", [1.0, np.nan, 2.0], "give numbers")
    with pytest.raises(ValueError, match=r"s contains NaN or inf \(inf\)"):
        finite("s", torch.tensor(float("inf"), requires_grad=True))
    with pytest.raises(TypeError, match="expected numbers, got 'abc'"):
        finite("s", "abc")
    big = torch.tensor([1e308, -1e-308])
    assert finite("u", big) is big  # extreme but finite: returned as given


def test_positive_in_range_and_count():
    from bayespd.validate import count, in_range, positive
    with pytest.raises(ValueError, match=r"h must be positive, got -1: pass a finite positive number"):
        positive("h", -1.0)
    assert positive("h", 1e-300) == 1e-300
    with pytest.raises(ValueError, match=r"p must lie in \(0, 1\), got 1.5: use 0.8"):
        in_range("p", 1.5, 0.0, 1.0, "use 0.8", closed=(False, False))
    assert in_range("p", 1.0, 0.0, 1.0, "use 0.8") == 1.0
    with pytest.raises(ValueError, match=r"n must be an integer >= 1, got 0: ask for one"):
        count("n", 0, 1, "ask for one")
    for bad in (True, 2.0, "3"):
        with pytest.raises(TypeError, match="n must be an integer"):
            count("n", bad)
    assert count("n", np.int64(7)) == 7


def test_files_and_devices(tmp_path):
    from bayespd.validate import device, readable_file, reading
    with pytest.raises(FileNotFoundError, match="no mesh file .*nothing.msh: check the path"):
        readable_file(tmp_path / "nothing.msh", "mesh file")
    with pytest.raises(ValueError, match=r"cannot read .*a.nc as a tree \(OSError: torn\): redo it"):
        with reading(tmp_path / "a.nc", "a tree", "redo it"):
            raise OSError("torn")
    with pytest.raises(ValueError, match="device='gpu' is not a torch device: use 'cpu'"):
        device("device", "gpu")
    with pytest.raises(ValueError, match=r"device='cuda:99': this machine has \d+ CUDA device"):
        device("device", "cuda:99")
    assert device("device", None) is None and device("device", "cpu") == torch.device("cpu")
