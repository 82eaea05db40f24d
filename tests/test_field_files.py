"""read_field: VIC CSV, .npz, NetCDF and DICe files written and read back; bad files refused."""
import numpy as np
import pytest
import xarray as xr

import bayespd as bp
from bayespd.dic import frame_data, read_dice
from tests.test_dic import write_frame
from tests.test_fields import X, Y, affine, grids

VIC_HEADER = '"x","y","X","Y","U","V","sigma","exx"'


def write_vic(path):
    """A VIC-3D-style export: image x, y (pixels, step 10), metric X, Y, U, V (mm, 0.05 mm per
    pixel), sigma -1 for a failed subset, a NaN subset, one row with empty entries, one row
    with no position (dropped)."""
    lines = [VIC_HEADER]
    for j, y in enumerate(Y):
        for i, x in enumerate(X):
            u, v = affine(np.array([x, y]))
            sigma = -1.0 if (i, j) == (1, 0) else 0.002
            U = "nan" if (i, j) == (2, 1) else f"{u * 0.01:.10g}"
            lines.append(f"{10 * x:g},{10 * y:g},{0.5 * x:.10g},{0.5 * y:.10g},{U},{v * 0.01:.10g},{sigma},0.001")
    lines[-1] = "40,120,2,6,,,,"  # the last subset exported empty
    lines.append(",,,,,,,")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_vic_csv_round_trip(tmp_path):
    field = bp.read_field(write_vic(tmp_path / "vic.csv"))  # the metric columns X, Y, U, V
    assert field.points.shape == (15, 2) and field.particles.h == pytest.approx(0.5)
    expected = 0.01 * affine(2 * field.points)
    valid = field.valid[:, 0]
    assert np.array_equal(np.flatnonzero(~valid), [1, 7, 14])
    assert np.abs(field.y[valid] - expected[valid]).max() < 1e-12
    assert field.sigma[0] == pytest.approx(0.002)
    image = bp.read_field(tmp_path / "vic.csv", columns={"x": "x", "y": "y", "u": "U", "v": "V", "sigma": "sigma"},
                          scale=0.05, flip_y=True)  # pixels, y down, to mm, y up (U, V scaled too)
    assert np.array_equal(image.valid, field.valid)
    assert np.allclose(image.points, field.points * [1, -1], rtol=0, atol=1e-12)
    assert np.allclose(image.y[valid], 0.05 * field.y[valid] * [1, -1], rtol=0, atol=1e-14)


def test_npz_round_trip_in_both_orders(tmp_path):
    for order in ("xy", "ij"):
        u, v = grids(order)
        np.savez(tmp_path / f"{order}.npz", x=X, y=Y, u=u, v=v, valid=np.ones_like(u, dtype=bool))
        field = bp.read_field(tmp_path / f"{order}.npz", order=order)
        assert np.array_equal(field.y, affine(field.points))
    u, v = grids("ij")
    with pytest.raises(ValueError, match="order='xy'.*transposed"):
        bp.read_field(tmp_path / "ij.npz", order="xy")
    np.savez(tmp_path / "square.npz", x=X[:3], y=Y, u=np.zeros((3, 3)), v=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="square 3 x 3 grid"):
        bp.read_field(tmp_path / "square.npz")


def test_netcdf_round_trip_takes_the_order_from_the_dims(tmp_path):
    u, v = grids("ij")
    sigma = np.full(u.shape, 0.01)
    sigma[3, 1] = np.nan
    ds = xr.Dataset({"u": (("x", "y"), u), "v": (("x", "y"), v), "sigma": (("x", "y"), sigma)},
                    coords={"x": X, "y": Y})
    ds.to_netcdf(tmp_path / "field.nc", engine="h5netcdf")
    field = bp.read_field(tmp_path / "field.nc")
    assert np.array_equal(np.flatnonzero(~field.valid[:, 0]), [5 * 1 + 3])
    keep = field.valid[:, 0]
    assert np.array_equal(field.y[keep], affine(field.points)[keep])
    with pytest.raises(ValueError, match="order 'ij'"):
        bp.read_field(tmp_path / "field.nc", order="xy")


def test_dice_frame_is_read_through_read_dice(tmp_path):
    for frame in (2, 10):
        write_frame(tmp_path, frame)
    pattern = str(tmp_path / "DICe_solution_*.txt")
    with pytest.raises(ValueError, match="frames \\[2, 10\\]: pass frame="):
        bp.read_field(pattern)
    field = bp.read_field(pattern, frame=2, scale=0.1, flip_y=True)
    points, y, mask = frame_data(read_dice(pattern), 2, 0.1, flip_y=True)
    assert np.allclose(field.points, points) and np.array_equal(field.valid, mask)
    assert np.array_equal(field.y[mask], y[mask]) and field.particles.h == pytest.approx(1.0)


def test_bad_files_are_refused_by_name(tmp_path):
    with pytest.raises(FileNotFoundError, match="no field file"):
        bp.read_field(tmp_path / "absent.csv")
    (tmp_path / "field.vtk").write_text("x")
    with pytest.raises(ValueError, match="unknown field file type '.vtk'"):
        bp.read_field(tmp_path / "field.vtk")
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="bad.csv has the columns \\['a', 'b'\\].*columns="):
        bp.read_field(tmp_path / "bad.csv")
    with pytest.raises(ValueError, match="lacks the column\\(s\\) \\['X'\\]"):
        bp.read_field(tmp_path / "bad.csv", columns={"x": "X", "y": "a", "u": "a", "v": "b"})
    (tmp_path / "text.csv").write_text("X,Y,U,V\n1,2,a,4\n")
    with pytest.raises(ValueError, match="non-numeric entries in the column\\(s\\) \\['U'\\]"):
        bp.read_field(tmp_path / "text.csv")
    np.savez(tmp_path / "partial.npz", x=X, y=Y, u=np.zeros((3, 5)))
    with pytest.raises(ValueError, match="partial.npz lacks \\['v'\\]"):
        bp.read_field(tmp_path / "partial.npz")
    for name in ("garbage.npz", "garbage.nc"):
        (tmp_path / name).write_bytes(b"\x00\x01not a grid")
        with pytest.raises(ValueError, match=f"cannot read .*{name}"):
            bp.read_field(tmp_path / name)
    with pytest.raises(ValueError, match="scale must be positive"):
        bp.read_field(tmp_path / "partial.npz", scale=0.0)
    with pytest.raises(ValueError, match="columns= names the columns of a VIC .csv"):
        bp.read_field(tmp_path / "partial.npz", columns={"x": "x"})
