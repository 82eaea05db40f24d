"""ParaView output read back with meshio (.vtu) and an XML parser (.pvd): exact round trips."""
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.vtk import Series, write_vtu


def test_particles_and_fields_round_trip(tmp_path, rng):
    p = bp.grid_2d(4.0, 3.0, 0.5)
    u = torch.as_tensor(rng.normal(size=(p.n, 2))) / 3  # digits that need all 17 to round-trip
    damage = rng.uniform(size=p.n)
    broken = rng.integers(0, 5, size=p.n)
    write_vtu(tmp_path / "plate.vtu", p, displacement=u, damage=damage, broken=broken)
    mesh = meshio.read(tmp_path / "plate.vtu")
    np.testing.assert_array_equal(mesh.points, np.c_[p.x, np.zeros(p.n)])
    np.testing.assert_array_equal(mesh.point_data["displacement"], np.c_[u.numpy(), np.zeros(p.n)])
    np.testing.assert_array_equal(mesh.point_data["damage"], damage)
    np.testing.assert_array_equal(mesh.point_data["broken"], broken)
    np.testing.assert_array_equal(mesh.point_data["volume"], p.volume)
    np.testing.assert_array_equal(mesh.cells_dict["vertex"].ravel(), np.arange(p.n))
    assert sorted(f.name for f in tmp_path.iterdir()) == ["plate.vtu"]  # no temporary left behind


def test_3d_points_and_a_bad_field(tmp_path, rng):
    x = rng.normal(size=(7, 3))
    write_vtu(tmp_path / "cloud.vtu", x, stress=np.arange(21.0).reshape(7, 3))
    mesh = meshio.read(tmp_path / "cloud.vtu")
    np.testing.assert_array_equal(mesh.points, x)
    np.testing.assert_array_equal(mesh.point_data["stress"], np.arange(21.0).reshape(7, 3))
    with pytest.raises(ValueError, match=r"field 'damage' must be numbers of shape \(7,\)"):
        write_vtu(tmp_path / "bad.vtu", x, damage=np.zeros(6))


def test_series_writes_a_pvd_collection(tmp_path):
    p = bp.grid_2d(2.0, 1.0, 0.5)
    series = Series(tmp_path / "crack.pvd")
    times = [0.0, 0.5, 1.25]
    for k, t in enumerate(times):
        series.write(t, p, damage=np.full(p.n, 0.1 * k))
    datasets = ET.parse(tmp_path / "crack.pvd").getroot().find("Collection").findall("DataSet")
    assert [float(d.get("timestep")) for d in datasets] == times
    assert [d.get("file") for d in datasets] == ["crack_0000.vtu", "crack_0001.vtu", "crack_0002.vtu"]
    for k, d in enumerate(datasets):
        np.testing.assert_array_equal(meshio.read(tmp_path / d.get("file")).point_data["damage"], 0.1 * k)
    with pytest.raises(ValueError, match="times must increase"):
        series.write(1.0, p)
