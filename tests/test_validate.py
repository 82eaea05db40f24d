"""bayespd/validate.py: the shared checks name the parameter, the value and the fix in every
message, and return extreme but valid values as given."""
import numpy as np
import pytest
import torch

from bayespd.validate import count, device, finite, in_range, positive, readable_file, reading


def test_finite_names_the_bad_entry_and_the_fix():
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
