"""Particles from meshes: volumes tile the body exactly, centroids are exact, bad meshes refused."""
import ast
import itertools
from pathlib import Path

import meshio
import numpy as np
import pytest

import bayespd
from bayespd.meshes import from_mesh


def lattice(counts, extent, rng=None, jitter=0.0):
    """Nodes of a structured grid (last axis fastest); interior nodes moved by up to jitter * spacing."""
    axes = [np.linspace(0, e, c + 1) for c, e in zip(counts, extent)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(counts))
    interior = np.all((nodes > 0) & (nodes < extent), axis=1)
    if rng is not None:
        step = np.asarray(extent) / counts
        nodes[interior] += jitter * step * rng.uniform(-1, 1, size=(interior.sum(), len(counts)))
    return nodes


def cells(counts, corners):
    """Connectivity of the structured cells, corners in VTK order as offsets per axis."""
    ids = np.arange(np.prod(np.add(counts, 1))).reshape(np.add(counts, 1))
    return np.array([[ids[tuple(np.add(start, c))] for c in corners]
                     for start in itertools.product(*[range(c) for c in counts])])


QUAD = [(0, 0), (1, 0), (1, 1), (0, 1)]
HEX = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
KUHN = [(0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6)]  # 6 tets per hex


def test_structured_quads_are_the_grid_cells(tmp_path):
    nodes = lattice((6, 4), (3.0, 2.0))
    flat = np.c_[nodes, np.full(len(nodes), 7.0)]  # 3D points, all z equal
    meshio.write(tmp_path / "plate.vtu", meshio.Mesh(flat, [("quad", cells((6, 4), QUAD))]))
    p = from_mesh(tmp_path / "plate.vtu", thickness=2.0)
    assert p.dim == 2 and p.thickness == 2.0 and p.h == pytest.approx(0.5, rel=1e-12)
    centres = np.array(list(itertools.product(0.25 + 0.5 * np.arange(6), 0.25 + 0.5 * np.arange(4))))
    np.testing.assert_allclose(p.x, centres, rtol=0, atol=1e-14)
    np.testing.assert_allclose(p.volume, 0.5, rtol=1e-14)


def test_warped_mixed_2d_mesh_tiles_the_rectangle(tmp_path, rng):
    """Jittered quads, half of them split into triangles: the areas sum to the rectangle's and
    the area-weighted centroids to its centre (exact cell centroids)."""
    nodes = lattice((6, 4), (3.0, 2.0), rng, jitter=0.3)
    quads = cells((6, 4), QUAD)
    tris = np.concatenate([quads[::2][:, [0, 1, 2]], quads[::2][:, [0, 2, 3]]])
    mesh = meshio.Mesh(nodes, [("quad", quads[1::2]), ("triangle", tris), ("line", quads[:3, :2])])
    meshio.write(tmp_path / "mixed.msh", mesh, file_format="gmsh22")
    p = from_mesh(tmp_path / "mixed.msh")
    assert p.n == len(quads[1::2]) + len(tris)
    assert p.volume.sum() == pytest.approx(6.0, rel=1e-12)
    np.testing.assert_allclose(p.volume @ p.x / p.volume.sum(), [1.5, 1.0], rtol=1e-12)


@pytest.mark.parametrize("kind", ["hexahedron", "tetra"])
def test_warped_3d_mesh_tiles_the_box(tmp_path, rng, kind):
    nodes = lattice((4, 3, 2), (2.0, 1.0, 1.5), rng, jitter=0.3)
    hexes = cells((4, 3, 2), HEX)
    volume_cells = hexes if kind == "hexahedron" else hexes[:, KUHN].reshape(-1, 4)
    boundary = hexes[:4, :4]  # some faces, as .msh files carry them: ignored
    meshio.write(tmp_path / "box.vtu", meshio.Mesh(nodes, [(kind, volume_cells), ("quad", boundary)]))
    p = from_mesh(tmp_path / "box.vtu")
    assert p.dim == 3 and p.n == len(volume_cells)
    assert p.volume.sum() == pytest.approx(3.0, rel=1e-12)
    np.testing.assert_allclose(p.volume @ p.x / p.volume.sum(), [1.0, 0.5, 0.75], rtol=1e-12)


def test_frustum_hexahedron_volume_and_centroid(tmp_path):
    """A square frustum (base 2 x 2, top 1 x 1, height 1): V = (4 + 1 + 2) / 3 = 7/3 and
    z_c = (A1 + 2 sqrt(A1 A2) + 3 A2) / (4 (A1 + sqrt(A1 A2) + A2)) = 11/28."""
    base = [(0, 0, 0), (2, 0, 0), (2, 2, 0), (0, 2, 0)]
    top = [(0.5, 0.5, 1), (1.5, 0.5, 1), (1.5, 1.5, 1), (0.5, 1.5, 1)]
    meshio.write(tmp_path / "frustum.vtu", meshio.Mesh(np.array(base + top, float), [("hexahedron", [list(range(8))])]))
    p = from_mesh(tmp_path / "frustum.vtu")
    assert p.volume[0] == pytest.approx(7 / 3, rel=1e-14)
    np.testing.assert_allclose(p.x[0], [1.0, 1.0, 11 / 28], rtol=1e-14)


def test_errors_name_the_fix(tmp_path):
    with pytest.raises(FileNotFoundError, match="no mesh file .*nowhere.msh: check the path"):
        from_mesh(tmp_path / "nowhere.msh")
    wedge = meshio.Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]], float),
                        [("wedge", [list(range(6))]), ("line", [[0, 1]])])
    meshio.write(tmp_path / "wedge.vtu", wedge)
    with pytest.raises(ValueError, match=r"3D mesh with cells \['line', 'wedge'\].*tetra and hexahedron"):
        from_mesh(tmp_path / "wedge.vtu")


def test_core_imports_no_meshio():
    """meshio is optional (bayespd[mesh]): no bayespd module imports it at module level."""
    for source in Path(bayespd.__file__).parent.rglob("*.py"):
        for node in ast.parse(source.read_text()).body:
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            assert not any(n.split(".")[0] == "meshio" for n in names), source


@pytest.mark.parametrize("name, content", [
    ("garbage.msh", b"$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n3\n1 0 0\n"),  # truncated in a node
    ("binary.vtu", bytes(range(256)) * 4),
    ("plate.unknown", b"1 2 3\n"),
])
def test_malformed_mesh_files_are_named(tmp_path, name, content):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(ValueError, match=rf"cannot read .*{name} as a mesh \(.*\): pass a complete mesh file"):
        from_mesh(tmp_path / name)


def test_cells_pointing_past_the_nodes_are_refused(tmp_path):
    nodes = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    meshio.write(tmp_path / "bad.vtu", meshio.Mesh(nodes, [("triangle", np.array([[0, 1, 2], [0, 1, 5]]))]))
    with pytest.raises(ValueError, match=r"bad.vtu: a triangle cell refers to a node outside 0..2"):
        from_mesh(tmp_path / "bad.vtu")
