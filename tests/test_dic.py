"""DICe solution files: header lines, extra columns, failed subsets, NaN, frame order."""
import numpy as np
import pytest

from bayespd.dic import frame_data, read_dice

HEADER = """***
*** Digital Image Correlation Engine (DICe), (git sha1: v1.0) Copyright 2015 NTESS
***
*** Subset size: 27
*** Step size: x 10 y 10 (-1 implies not regular grid)
*** Coordinates given with (0,0) as upper left corner of image, x positive right, y positive down
***
"""
COLUMNS = ["SUBSET_ID", "COORDINATE_X", "COORDINATE_Y", "DISPLACEMENT_X", "DISPLACEMENT_Y", "SIGMA", "GAMMA",
           "STATUS_FLAG", "VSG_STRAIN_XX"]
XY = [(46.0, 366.0), (56.0, 366.0), (46.0, 376.0), (56.0, 376.0)]


def rows(frame):
    """Per subset: u, v, sigma, status. Frame 2: subset 1 failed (SIGMA -1, flag 11 =
    MAX_ITERATIONS_REACHED), subset 2 has a NaN; frame 10: subset 3 only averaged (flag 15)."""
    table = [[0.125 * frame + k, -0.0625 * frame - k, 0.01 * (k + 1), 4] for k in range(4)]
    if frame == 2:
        table[1] = [0.0, 0.0, -1.0, 11]
        table[2][1] = float("nan")
    if frame == 10:
        table[3][3] = 15
    return table


def write_frame(folder, frame, columns=COLUMNS, order=(0, 1, 2, 3), xy=XY, suffix=""):
    lines = [",".join(columns)]
    for k in order:
        u, v, sigma, flag = rows(frame)[k]
        values = {"SUBSET_ID": str(k), "COORDINATE_X": f"{xy[k][0]:.4E}", "COORDINATE_Y": f"{xy[k][1]:.4E}",
                  "DISPLACEMENT_X": f"{u:.4E}", "DISPLACEMENT_Y": f"{v:.4E}", "SIGMA": f"{sigma:.4E}",
                  "GAMMA": "2.4682E-03", "STATUS_FLAG": f"{flag:.4E}", "VSG_STRAIN_XX": "-5.4077E-04"}
        lines.append(",".join(values[c] for c in columns))
    path = folder / f"DICe_solution_{frame}{suffix}.txt"
    path.write_text(HEADER + "\n".join(lines) + "\n")  # a NaN is written NAN, as C's %E does
    return path


@pytest.fixture
def run(tmp_path):
    write_frame(tmp_path, 10, order=(3, 1, 0, 2), suffix=".2")  # as a 2-process run names it
    write_frame(tmp_path, 1)
    write_frame(tmp_path, 2)
    return tmp_path


def test_reads_frames_in_numeric_order_with_values_and_mask(run):
    ds = read_dice(str(run / "DICe_solution_*.txt"))
    assert ds["displacement"].dims == ("frame", "point", "component")
    assert ds["frame"].values.tolist() == [1, 2, 10]  # 10 after 2, not after 1
    assert ds["component"].values.tolist() == ["x", "y"] and ds["point"].values.tolist() == [0, 1, 2, 3]
    np.testing.assert_array_equal(np.stack([ds["x"], ds["y"]], axis=1), XY)
    for i, frame in enumerate([1, 2, 10]):
        expected = np.array([[float(f"{a:.4E}") for a in r] for r in rows(frame)])  # as written
        np.testing.assert_array_equal(ds["displacement"].values[i], expected[:, :2])
        np.testing.assert_array_equal(ds["sigma"].values[i], expected[:, 2])
        np.testing.assert_array_equal(ds["status"].values[i], expected[:, 3].astype(int))
    np.testing.assert_array_equal(ds["mask"].values, [[1, 1, 1, 1], [1, 0, 0, 1], [1, 1, 1, 0]])
    assert ds["status"].dtype.kind == "i" and ds["mask"].dtype == bool


def test_frame_data_for_a_model(run):
    ds = read_dice(sorted(run.glob("*.txt")))
    points, y, mask = frame_data(ds, 2, scale=0.05, origin=(0.0, 20.0), flip_y=True)
    np.testing.assert_allclose(points, [[0.05 * x, 20.0 - 0.05 * yy] for x, yy in XY], rtol=1e-15)
    np.testing.assert_allclose(y[0], [0.05 * 0.25, 0.05 * 0.125], rtol=1e-15)  # v = -0.125 px, flipped
    assert np.isnan(y[2, 1]) and mask.shape == (4, 2)
    np.testing.assert_array_equal(mask[:, 0], [True, False, False, True])
    with pytest.raises(ValueError, match=r"no frame 3: the data set has frames \[1, 2, 10\]"):
        frame_data(ds, 3)


def test_missing_columns_are_named(tmp_path):
    path = write_frame(tmp_path, 1, columns=[c for c in COLUMNS if c not in ("SIGMA", "STATUS_FLAG")])
    with pytest.raises(ValueError, match=r"DICe_solution_1.txt lacks the column\(s\) \['SIGMA', 'STATUS_FLAG'\]"):
        read_dice([path])


def test_frames_on_different_subsets_are_refused(tmp_path):
    write_frame(tmp_path, 1)
    write_frame(tmp_path, 2, xy=[(46.0, 366.0), (56.0, 366.0), (46.0, 376.0), (66.0, 376.0)])
    with pytest.raises(ValueError, match="DICe_solution_2.txt does not list the same subsets"):
        read_dice(str(tmp_path / "*.txt"))


def test_bad_file_lists(tmp_path):
    with pytest.raises(FileNotFoundError, match="no DICe files match"):
        read_dice(str(tmp_path / "*.txt"))
    (tmp_path / "notes.txt").write_text(HEADER)
    with pytest.raises(ValueError, match="no frame number"):
        read_dice([tmp_path / "notes.txt"])


def test_a_file_truncated_mid_row_names_the_file_and_line(run):
    path = run / "DICe_solution_2.txt"
    text = path.read_text()
    path.write_text(text[: text.rindex(",", 0, len(text) - 30)])  # cut inside the last subset's row
    with pytest.raises(ValueError, match=r"DICe_solution_2.txt, line 12: \d fields where the header has 9 "
                                         r"\(a truncated or damaged file\?\)"):
        read_dice(str(run / "DICe_solution_*.txt"))


def test_an_extra_field_names_the_line(tmp_path):
    path = write_frame(tmp_path, 1)
    lines = path.read_text().splitlines()
    lines[9] += ",7.0"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"DICe_solution_1.txt, line 10: 10 fields where the header has 9"):
        read_dice(path)


@pytest.mark.parametrize("content, match", [
    (b"\x89PNG\r\n\x1a\n\xff\xfe\x00\x00", r"cannot read .*DICe_solution_1.txt as a DICe solution file.*UnicodeDecodeError"),
    (b"COORDINATE_X,COORDINATE_Y\n\x00\x01,2\n", r"DICe_solution_1.txt is a binary file"),
])
def test_binary_files_are_named(tmp_path, content, match):
    path = tmp_path / "DICe_solution_1.txt"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=match):
        read_dice(path)


def test_a_file_without_final_newline_and_trailing_delimiters_is_read(tmp_path):
    """Rows ending with the delimiter, as some DICe builds write them, and no final newline."""
    path = write_frame(tmp_path, 1)
    path.write_text(",\n".join(path.read_text().splitlines()[7:]) + ",")
    ds = read_dice(path)
    assert ds.sizes["point"] == 4 and np.isfinite(ds["displacement"].values).all()


@pytest.mark.parametrize("kw, match", [
    ({"scale": 0.0}, "scale must be positive, got 0: pass the model units per pixel"),
    ({"scale": float("nan")}, "scale contains NaN or inf"),
    ({"origin": (0.0, float("inf"))}, r"origin contains NaN or inf \(1 of 2 entries"),
])
def test_frame_data_refuses_a_bad_scale_or_origin(run, kw, match):
    with pytest.raises(ValueError, match=match):
        frame_data(read_dice(str(run / "DICe_solution_*.txt")), 1, **kw)
