"""MD records: round trip with units, the settings-hash cache, and refusals that name the fix."""
import numpy as np
import pytest

from bayespd.learn import md_files


def _record(rng, frames=3, n=20, **kw):
    x = rng.uniform(0, 10, (n, 2))
    u = 0.01 * rng.normal(size=(frames, n, 2))
    return md_files.record(x, u, np.zeros_like(u), np.full(n, 12.011), np.arange(frames) * 0.05,
                           kind="test", settings={"n": n}, **kw)


def test_round_trip_keeps_arrays_units_and_settings(rng, tmp_path):
    ds = _record(rng)
    back = md_files.read_md(md_files.write_md(ds, tmp_path / "r.nc"))
    np.testing.assert_array_equal(back["U"].values, ds["U"].values)
    assert back["U"].attrs["units"] == "angstrom" and back["B"].attrs["units"] == "eV/angstrom"
    assert back.attrs["settings_hash"] == md_files.settings_hash("test", {"n": 20})
    assert not list(tmp_path.glob("*.tmp"))


def test_cache_makes_once_and_a_new_setting_makes_again(rng, tmp_path):
    calls = []
    make = lambda: calls.append(1) or _record(rng)
    first = md_files.cached("test", {"n": 20}, tmp_path, make)
    second = md_files.cached("test", {"n": 20}, tmp_path, make)
    np.testing.assert_array_equal(first["U"].values, second["U"].values)
    assert len(calls) == 1
    md_files.cached("test", {"n": 21}, tmp_path, make)
    assert len(calls) == 2 and len(list(tmp_path.glob("test-*.nc"))) == 2


def test_missing_array_wrong_units_and_nan_are_refused(rng, tmp_path):
    ds = _record(rng)
    with pytest.raises(ValueError, match=r"lacks the array\(s\) \['B'\]: remake it"):
        md_files.read_md(md_files.write_md(ds.drop_vars("B"), tmp_path / "a.nc"))
    bad = ds.copy(deep=True)
    bad["U"].attrs["units"] = "nm"
    with pytest.raises(ValueError, match="U is in 'nm', not 'angstrom': convert it"):
        md_files.read_md(md_files.write_md(bad, tmp_path / "b.nc"))
    bad = ds.copy(deep=True)
    bad["U"].values[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match="diverged"):
        md_files.check_md(bad)


def test_atoms_that_left_the_sheet_are_refused_with_the_frame(rng):
    ds = _record(rng)
    ds["U"].values[2, 5, 1] = 30.0
    with pytest.raises(ValueError, match=r"1 atom\(s\) left the sheet .* at frame 2: keep the frames before it"):
        md_files.check_md(ds)
    assert md_files.check_md(ds.isel(frame=slice(0, 2))) is not None
    periodic = _record(rng, periodic=True, box=[10.0, 10.0])
    periodic["U"].values[1, 0, 0] = 6.0
    with pytest.raises(ValueError, match="at frame 1"):
        md_files.check_md(periodic)
