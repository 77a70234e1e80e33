import pathlib

import meshio
import numpy as np
import pytest

from jaxvisco._fem._elements import element_type
from jaxvisco._fem._generators import box, lshape_mesh, rectangle
from jaxvisco._fem._mesh import Mesh

DATA = pathlib.Path(__file__).parent / "data"
EXAMPLE_MSH = pathlib.Path(__file__).parent.parent / "examples" / "data" / "lshape2d.msh"
ELEMENTS_2D = ["quad4", "tri3", "tri6", "quad8", "quad9"]
ELEMENTS_3D = ["hex8", "tet4", "tet10", "hex20", "hex27"]


def _sorted_rows(a):
    a = np.round(np.asarray(a), 12)
    return a[np.lexsort(a.T[::-1])]


# ------------------------------------------------------------------ generators


def test_lshape_2d_counts():
    m = lshape_mesh(2, 1)
    assert (m.cell_type, m.dim, m.n_cells, m.n_nodes) == ("quad4", 2, 39, 56)
    assert len(np.unique(np.asarray(m.points), axis=0)) == 56  # no duplicates
    assert m.points.dtype == np.float64 and m.cells.dtype == np.int32


@pytest.mark.parametrize("dim,name", [(2, n) for n in ELEMENTS_2D] + [(3, n) for n in ELEMENTS_3D])
def test_lshape_every_element(dim, name):
    m1 = lshape_mesh(dim, 1, name).validate()
    assert m1.cell_type == name
    assert np.isclose(float(m1.volume()), 39.0 if dim == 2 else 117.0, rtol=1e-12)
    m2 = lshape_mesh(dim, 2, name).validate()
    assert m2.n_cells == 2**dim * m1.n_cells
    assert np.isclose(float(m2.volume()), float(m1.volume()), rtol=1e-12)
    # Shared nodes are merged: no two nodes coincide.
    assert len(np.unique(np.round(np.asarray(m2.points), 12), axis=0)) == m2.n_nodes
    # Sum of the quadrature weights is the volume too (all positive).
    qd = m1.quadrature_data()
    assert np.all(qd.JxW > 0)
    assert np.isclose(float(qd.JxW.sum()), float(m1.volume()), rtol=1e-12)


def test_rectangle_and_box():
    r = rectangle(3, 2, lx=1.5, ly=0.5, cell_type="tri6", origin=(1.0, -1.0)).validate()
    assert r.n_cells == 12 and np.isclose(float(r.volume()), 0.75)
    pts = np.asarray(r.points)
    assert np.allclose(pts.min(0), [1.0, -1.0]) and np.allclose(pts.max(0), [2.5, -0.5])
    b = box(2, 3, 1, 2.0, 3.0, 0.5, cell_type="tet10").validate()
    assert b.n_cells == 36 and np.isclose(float(b.volume()), 3.0)
    with pytest.raises(ValueError, match="nx must be an integer >= 1, got 0"):
        rectangle(0, 2)
    with pytest.raises(ValueError, match="'hex8' is 3D"):
        rectangle(2, 2, cell_type="hex8")
    with pytest.raises(ValueError, match="dim must be 2 or 3, got 4"):
        lshape_mesh(4)


# ------------------------------------------------------------------ Abaqus files


def test_read_abaqus_medium_matches_generated():
    m = Mesh.read(DATA / "LShapeH1Medium.inp").validate()
    assert (m.cell_type, m.dim, m.n_cells, m.n_nodes) == ("hex8", 3, 117, 224)
    assert np.isclose(float(m.volume()), 117.0)
    g = lshape_mesh(3, 1)
    assert g.n_cells == m.n_cells and np.isclose(float(g.volume()), float(m.volume()))
    # meshio ignores the *Instance rotation: coordinates are the untransformed block.
    np.testing.assert_allclose(_sorted_rows(g.points), _sorted_rows(m.points))


def test_read_abaqus_hex20():
    m = Mesh.read(DATA / "LShapeH2SerendipityCoarse.inp").validate()
    assert (m.cell_type, m.n_cells, m.n_nodes) == ("hex20", 117, 768)
    assert np.isclose(float(m.volume()), 117.0, rtol=1e-12)
    # Abaqus C3D20 order == meshio/VTK hexahedron20: every mid-edge node sits at the
    # midpoint of its edge's corners.
    X = np.asarray(m.points)[np.asarray(m.cells)]
    ref = element_type("hex20").reference_nodes()
    corners = ref[:8]
    for k in range(8, 20):
        a, b = np.flatnonzero(np.all(np.abs(corners - ref[k]) <= 1, axis=1))
        np.testing.assert_allclose(X[:, k], 0.5 * (X[:, a] + X[:, b]), atol=1e-12)


def test_read_abaqus_coarse():
    m = Mesh.read(DATA / "LShapeH1.inp").validate()
    assert (m.cell_type, m.n_cells) == ("hex8", 36)
    assert np.isclose(float(m.volume()), 117.0)


# ------------------------------------------------------------------ round trips


def test_example_msh_reads_back():
    m = Mesh.read(EXAMPLE_MSH).validate()
    assert (m.cell_type, m.dim, m.n_cells, m.n_nodes) == ("quad4", 2, 39, 56)
    assert np.isclose(float(m.volume()), 39.0)


@pytest.mark.parametrize("suffix,fmt", [(".vtu", None), (".msh", "gmsh22"), (".xdmf", None)])
@pytest.mark.parametrize("dim,name", [(2, "quad9"), (3, "hex8"), (3, "tet10")])
def test_write_read_round_trip(tmp_path, suffix, fmt, dim, name):
    m = lshape_mesh(dim, 1, name)
    path = tmp_path / f"mesh{suffix}"
    m.write(path, file_format=fmt)
    r = Mesh.read(path)
    assert r.cell_type == m.cell_type and r.dim == m.dim
    np.testing.assert_array_equal(r.cells, m.cells)
    np.testing.assert_allclose(r.points, m.points, atol=1e-14)


# ------------------------------------------------------------------ errors


def _quad():
    return np.array([[0.0, 0], [1, 0], [1, 1], [0, 1]]), np.array([[0, 1, 2, 3]])


def test_validate_inverted():
    p, c = _quad()
    p = np.concatenate([p, p + [1.0, 0]])
    cells = np.array([[0, 1, 2, 3], [4, 7, 6, 5]])  # second one clockwise
    with pytest.raises(ValueError, match=r"element 1 is inverted: det J = -0\.25"):
        Mesh(points=p, cells=cells, cell_type="quad4").validate()


def test_validate_degenerate():
    p, c = _quad()
    p[2] = p[1]  # collapse an edge: det J vanishes at a corner
    with pytest.raises(ValueError, match=r"element 0 is degenerate: det J = 0"):
        Mesh(points=p, cells=c, cell_type="quad4").validate()
    p, c = _quad()
    with pytest.raises(ValueError, match=r"element 0 repeats a node index: \[0, 1, 1, 3\]"):
        Mesh(points=p, cells=[[0, 1, 1, 3]], cell_type="quad4").validate()


def test_validate_unused_node():
    p, c = _quad()
    p = np.concatenate([p, [[5.0, 5.0]]])
    with pytest.raises(ValueError, match="node 4 is used by no element"):
        Mesh(points=p, cells=c, cell_type="quad4").validate()


def test_constructor_errors():
    p, c = _quad()
    with pytest.raises(ValueError, match=r"cells must be a 2D array with 4 columns.*\(1, 3\)"):
        Mesh(points=p, cells=c[:, :3], cell_type="quad4")
    with pytest.raises(ValueError, match=r"points must be a 2D array with 2 or 3 columns.*\(4, 4\)"):
        Mesh(points=np.zeros((4, 4)), cells=c, cell_type="quad4")
    with pytest.raises(ValueError, match="'hex8' is 3D but points have 2"):
        Mesh(points=p, cells=np.zeros((1, 8), int), cell_type="hex8")
    with pytest.raises(ValueError, match="Unknown cell type 'pentagon'.*accepted"):
        Mesh(points=p, cells=c, cell_type="pentagon")
    with pytest.raises(ValueError, match="empty mesh: 4 points and 0 cells"):
        Mesh(points=p, cells=np.zeros((0, 4), int), cell_type="quad4")
    with pytest.raises(ValueError, match=r"element 0 has node indices \[0, 1, 2, 9\] outside \[0, 3\]"):
        Mesh(points=p, cells=[[0, 1, 2, 9]], cell_type="quad4")
    p[1, 0] = np.nan
    with pytest.raises(ValueError, match="node 1 has non-finite coordinates"):
        Mesh(points=p, cells=c, cell_type="quad4")
    m = Mesh(points=_quad()[0], cells=c, cell_type="quad")  # meshio name normalised
    assert m.cell_type == "quad4" and m.element.n_nodes == 4


def test_read_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.msh"):
        Mesh.read(tmp_path / "nope.msh")
    garbage = tmp_path / "garbage.vtu"
    garbage.write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match="could not read mesh file .*garbage.vtu"):
        Mesh.read(garbage)
    mixed = tmp_path / "mixed.vtu"
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]])
    meshio.Mesh(pts, [("quad", [[0, 1, 2, 3]]), ("triangle", [[1, 4, 2]])]).write(mixed)
    with pytest.raises(ValueError, match=r"mixed cell types \['quad', 'triangle'\]"):
        Mesh.read(mixed)
    m = Mesh.read(mixed, cell_type="quad4")  # picking one type works, pruning node 4
    assert (m.n_cells, m.n_nodes, m.dim) == (1, 4, 2)
    wedge = tmp_path / "wedge.vtu"
    meshio.Mesh(np.eye(3).tolist() + [[0, 0, 0], [0, 0, 2], [1, 0, 2]],
                [("wedge", [[0, 1, 2, 3, 4, 5]])]).write(wedge)  # fmt: skip
    with pytest.raises(ValueError, match="cell type 'wedge' .* not supported"):
        Mesh.read(wedge)
    surface = tmp_path / "surface.vtu"
    meshio.Mesh(pts + [0, 0, 1.0], [("quad", [[0, 1, 2, 3]])]).write(surface)
    with pytest.raises(ValueError, match="non-zero z"):
        Mesh.read(surface)


def test_read_keeps_unused_nodes_without_prune(tmp_path):
    path = tmp_path / "extra.vtu"
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [7, 7, 0]])
    meshio.Mesh(pts, [("quad", [[0, 1, 2, 3]])]).write(path)
    assert Mesh.read(path).n_nodes == 4
    raw = Mesh.read(path, prune=False)
    with pytest.raises(ValueError, match="node 4 is used by no element"):
        raw.validate()
