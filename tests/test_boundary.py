"""Boundary facets, dead surface loads and named mesh groups (Gmsh, Abaqus)."""

import pathlib
import shutil

import jax
import meshio
import numpy as np
import pytest

from jaxvisco._fem._boundary import (
    _boundary,
    _geometry,
    boundary_facets,
    facet_area,
    facet_type,
    facets_from_nodes,
    nodes_where,
    pressure_load,
    traction_load,
)
from jaxvisco._fem._elements import element_type
from jaxvisco._fem._generators import box, lshape_mesh, rectangle
from jaxvisco._fem._groups import read_mesh
from jaxvisco._fem._mesh import Mesh

DATA = pathlib.Path(__file__).parent / "data"
ELEMENTS_2D = ["tri3", "tri6", "quad4", "quad8", "quad9"]
ELEMENTS_3D = ["tet4", "tet10", "hex8", "hex20", "hex27"]
LINEAR = {"line2": "line2", "line3": "line2", "tri3": "tri3", "tri6": "tri3",
          "quad4": "quad4", "quad8": "quad4", "quad9": "quad4"}  # fmt: skip


def _mesh(name):
    """A small box/rectangle mesh; returns it, its boundary measure and facet count."""
    if name in ELEMENTS_2D:
        m = rectangle(3, 2, 1.5, 1.0, cell_type=name)
        return m, 5.0, 10
    m = box(2, 1, 2, 1.0, 0.5, 2.0, cell_type=name)
    n_quads = 2 * (2 * 1 + 1 * 2 + 2 * 2)
    return m, 2 * (1.0 * 0.5 + 0.5 * 2.0 + 1.0 * 2.0), n_quads * (2 if name.startswith("tet") else 1)


def _distorted(m):
    X = np.asarray(m.points)
    Y = X + 0.06 * np.sin(2.0 * X[:, ::-1] + 0.5 * X) * (1 + X.sum(1, keepdims=True))
    return Mesh(Y, m.cells, m.cell_type).validate()


def _mean_normals(m, facets):
    _, n = _geometry(m, facets)
    return np.asarray(n).sum(1)


@pytest.mark.parametrize("name", ELEMENTS_2D + ELEMENTS_3D)
def test_boundary_facets_count_measure_orientation(name):
    m, measure, count = _mesh(name)
    f = boundary_facets(m)
    assert f.shape == (count, element_type(facet_type(name)).n_nodes)
    assert np.isclose(facet_area(m, f), measure, rtol=1e-12)
    # Facet node order is the facet element's: on an affine mesh every node sits where
    # the linear facet through the corners puts the facet element's reference node.
    fe, lin = element_type(facet_type(name)), element_type(LINEAR[facet_type(name)])
    N = np.stack([np.asarray(lin.shape_functions(r)) for r in fe.reference_nodes()])
    X = np.asarray(m.points)[f]
    np.testing.assert_allclose(X, np.einsum("ac,fcd->fad", N, X[:, : lin.n_nodes]),
                               atol=1e-12)  # fmt: skip
    for mesh in (m, _distorted(m)):
        f, cell, _ = _boundary(mesh)
        P, C = np.asarray(mesh.points), np.asarray(mesh.cells)
        out = P[f].mean(1) - P[C[cell]].mean(1)
        assert np.all(np.sum(_mean_normals(mesh, f) * out, axis=1) > 0)


@pytest.mark.parametrize("name", ELEMENTS_2D + ELEMENTS_3D)
def test_traction_resultant_and_moment(name):
    m, measure, _ = _mesh(name)
    t = np.array([1.5, -2.0, 0.25])[: m.dim]
    for mesh in (m, _distorted(m)):
        f = boundary_facets(mesh)
        F = np.asarray(traction_load(mesh, f, t))
        np.testing.assert_allclose(F.sum(0), facet_area(mesh, f) * t, rtol=1e-12)
    # Consistent forces integrate linear fields exactly: sum_a X_a f_a^T = int X t^T dA.
    face = facets_from_nodes(m, nodes_where(m, lambda X: np.isclose(X[:, 0], X[:, 0].max())))
    F = np.asarray(traction_load(m, face, t))
    A = facet_area(m, face)
    P = np.asarray(m.points)
    centroid = np.r_[P[:, 0].max(), 0.5 * P[:, 1:].max(0)]
    np.testing.assert_allclose(P.T @ F, A * np.outer(centroid, t), atol=1e-12)
    # Per-facet tractions: the resultant is the area-weighted sum.
    tf = np.random.default_rng(0).standard_normal((len(face), m.dim))
    areas = np.array([facet_area(m, face[i : i + 1]) for i in range(len(face))])
    np.testing.assert_allclose(np.asarray(traction_load(m, face, tf)).sum(0), areas @ tf,
                               rtol=1e-12)  # fmt: skip


@pytest.mark.parametrize(
    "name,weights",
    [
        ("quad8", [1 / 6, 1 / 6, 2 / 3]),
        ("quad9", [1 / 6, 1 / 6, 2 / 3]),
        ("tri6", [1 / 6, 1 / 6, 2 / 3]),
        ("tet10", [0, 0, 0, 1 / 3, 1 / 3, 1 / 3]),
        ("hex20", [-1 / 12] * 4 + [1 / 3] * 4),
        ("hex27", [1 / 36] * 4 + [1 / 9] * 4 + [4 / 9]),
    ],
)
def test_consistent_quadratic_distribution(name, weights):
    """Uniform traction on one straight quadratic facet: the textbook nodal fractions."""
    m = rectangle(1, 1, 2.0, 1.0, cell_type=name) if name in ELEMENTS_2D else box(
        1, 1, 1, 2.0, 1.0, 3.0, cell_type=name)  # fmt: skip
    f = boundary_facets(m)
    one = f[:1]
    F = np.asarray(traction_load(m, one, np.ones(m.dim)))[:, 0]
    np.testing.assert_allclose(F[one[0]], facet_area(m, one) * np.array(weights), atol=1e-13)


@pytest.mark.parametrize("name", ["tri6", "quad8", "tet4", "hex8", "hex27"])
def test_pressure_closed_surface_and_face(name):
    m, _, _ = _mesh(name)
    closed = pressure_load(_distorted(m), boundary_facets(_distorted(m)), 2.0)
    np.testing.assert_allclose(np.asarray(closed).sum(0), 0.0, atol=1e-12)
    face = facets_from_nodes(m, nodes_where(m, lambda X: np.isclose(X[:, 1], 0.0)))
    F = np.asarray(pressure_load(m, face, 2.0))
    n = np.zeros(m.dim)
    n[1] = -1.0
    np.testing.assert_allclose(F.sum(0), -2.0 * facet_area(m, face) * n, atol=1e-12)
    per_facet = np.asarray(pressure_load(m, face, np.full(len(face), 2.0)))
    np.testing.assert_allclose(per_facet, F, atol=1e-14)


def test_loads_are_differentiable_in_the_load():
    m = box(1, 1, 1, cell_type="hex8")
    f = facets_from_nodes(m, nodes_where(m, lambda X: X[:, 2] > 0.99))
    g = jax.grad(lambda t: traction_load(m, f, t)[:, 2].sum())(np.zeros(3))
    np.testing.assert_allclose(np.asarray(g), [0.0, 0.0, 1.0], atol=1e-14)
    gp = jax.grad(lambda p: pressure_load(m, f, p)[:, 2].sum())(1.0)
    assert np.isclose(float(gp), -1.0)
    jitted = jax.jit(lambda t: traction_load(m, f, t))(np.ones(3))
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(traction_load(m, f, np.ones(3))))


def test_facets_from_nodes_and_nodes_where_on_a_box_face():
    m = box(2, 3, 2, 2.0, 3.0, 2.0, cell_type="hex20")
    top = nodes_where(m, lambda X: np.isclose(X[:, 2], 2.0))
    assert np.all(np.diff(top) > 0) and np.allclose(np.asarray(m.points)[top, 2], 2.0)
    f = facets_from_nodes(m, top)
    assert f.shape == (6, 8) and np.isclose(facet_area(m, f), 6.0)
    assert np.all(_mean_normals(m, f)[:, 2] > 0)
    # A node set with one face's worth of corners but no mid-side nodes holds no facet.
    corners = top[np.isclose(np.asarray(m.points)[top, :2] % 1.0, 0).all(1)]
    with pytest.raises(ValueError, match="no boundary facet has all its nodes"):
        facets_from_nodes(m, corners)


def test_bad_inputs_name_the_argument():
    m = rectangle(2, 1, cell_type="quad8")
    f = boundary_facets(m)
    with pytest.raises(ValueError, match=rf"must return a bool array of shape \({m.n_nodes},\)"):
        nodes_where(m, lambda X: X[:, 0])
    with pytest.raises(ValueError, match=r"got dtype bool and shape \(1,\)"):
        nodes_where(m, lambda X: np.array([True]))
    with pytest.raises(ValueError, match="predicate selects no node.*bounding box"):
        nodes_where(m, lambda X: X[:, 0] > 5)
    with pytest.raises(ValueError, match=r"facets must be .*shape \(n, 3\), got .*\(6, 2\)"
                       r".*quad8 meshes have line3 facets of 3 nodes"):
        traction_load(m, f[:, :2], [1.0, 0.0])
    with pytest.raises(ValueError, match=rf"facets holds node index 99 outside \[0, {m.n_nodes - 1}\]"):
        traction_load(m, np.where(f == f[0, 0], 99, f), [1.0, 0.0])
    with pytest.raises(ValueError, match=r"traction must have shape \(2,\) \(constant\) or "
                       r"\(6, 2\) \(one per facet\), got shape \(3,\)"):
        traction_load(m, f, [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="traction must be finite, got nan"):
        traction_load(m, f, [np.nan, 0.0])
    with pytest.raises(ValueError, match=r"pressure must have shape \(\) .* got shape \(2,\)"):
        pressure_load(m, f, [1.0, 2.0])
    with pytest.raises(ValueError, match="nodes must be a non-empty integer array"):
        facets_from_nodes(m, np.zeros(0, dtype=int))
    with pytest.raises(ValueError, match="cell type 'line2' has no facet type"):
        facet_type("line2")


# --------------------------------------------------------------------------- gmsh


def _gmsh_2d(tmp_path):
    """A 3x2 quad mesh with an unused node first (renumbered away by Mesh.read)."""
    m = rectangle(3, 2, 3.0, 2.0, cell_type="quad4")
    P = np.asarray(m.points)
    pts = np.column_stack([np.vstack([[9.0, 9.0], P]), np.zeros(len(P) + 1)])
    left = np.flatnonzero(np.isclose(P[:, 0], 0.0)) + 1
    tip = np.flatnonzero(np.isclose(P, [3.0, 2.0]).all(1)) + 1
    cells = [("quad", np.asarray(m.cells) + 1), ("line", np.c_[left[1:], left[:-1]]),
             ("line", np.c_[left[1:2], left[2:3]][:, ::-1]), ("vertex", tip[:, None])]
    tags = [np.full(len(c), t) for (_, c), t in zip(cells, (3, 1, 1, 2))]
    path = tmp_path / "beam.msh"
    meshio.Mesh(pts, cells, cell_data={"gmsh:physical": tags, "gmsh:geometrical": tags},
                field_data={"clamp": np.array([1, 1]), "tip": np.array([2, 0]),
                            "body": np.array([3, 2])}).write(path, file_format="gmsh22",
                                                             binary=False)  # fmt: skip
    return path


GMSH41 = """$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$PhysicalNames\n3\n0 2 "tip"
1 1 "clamp"\n2 3 "body"\n$EndPhysicalNames\n$Entities\n1 1 1 0\n1 2 1 0 1 2
1 0 0 0 0 1 0 1 1 0\n1 0 0 0 2 1 0 1 3 0\n$EndEntities\n$Nodes\n1 6 1 6\n2 1 0 6
1\n2\n3\n4\n5\n6\n0 0 0\n1 0 0\n2 0 0\n0 1 0\n1 1 0\n2 1 0\n$EndNodes\n$Elements
3 4 1 4\n0 1 15 1\n4 6\n1 1 1 1\n3 4 1\n2 1 3 2\n1 1 2 5 4\n2 2 3 6 5\n$EndElements\n"""


def test_gmsh_22_and_41_physical_groups(tmp_path):
    (tmp_path / "beam41.msh").write_text(GMSH41)
    for path in (_gmsh_2d(tmp_path), tmp_path / "beam41.msh"):
        mesh, g = read_mesh(path)
        ref = Mesh.read(path)
        np.testing.assert_array_equal(np.asarray(mesh.points), np.asarray(ref.points))
        np.testing.assert_array_equal(np.asarray(mesh.cells), np.asarray(ref.cells))
        P = np.asarray(mesh.points)
        assert g.names() == {"nodes": ["body", "clamp", "tip"], "cells": ["body"],
                             "facets": ["clamp"]}  # fmt: skip
        np.testing.assert_array_equal(g.node_group("clamp"), np.flatnonzero(P[:, 0] == 0))
        np.testing.assert_array_equal(P[g.node_group("tip")], [P.max(0)])
        np.testing.assert_array_equal(g.cell_group("body"), np.arange(mesh.n_cells))
        clamp = g.facet_group(mesh, "clamp")
        assert np.isclose(facet_area(mesh, clamp), P[:, 1].max())
        assert np.all(_mean_normals(mesh, clamp)[:, 0] < 0)  # outward: -x
        # The facet group equals the facets derived from its nodes.
        np.testing.assert_array_equal(
            np.sort(clamp, 0), np.sort(facets_from_nodes(mesh, g.node_group("clamp")), 0)
        )
        with pytest.raises(ValueError, match="node group 'tip' .* holds no boundary facet"):
            g.facet_group(mesh, "tip")
        with pytest.raises(ValueError, match=(
            rf"mesh '{path.name}' has no node group 'tipp'; node groups: \['body', "
            r"'clamp', 'tip'\]; cell groups: \['body'\]; facet groups: \['clamp'\]")):
            g.node_group("tipp")
        with pytest.raises(ValueError, match="has no node group 'Tip'"):  # case matters
            g.node_group("Tip")


def test_gmsh_3d_surface_group(tmp_path):
    m = box(2, 2, 1, 2.0, 2.0, 1.0, cell_type="hex20")
    P, C = np.asarray(m.points), np.asarray(m.cells)
    f = facets_from_nodes(m, nodes_where(m, lambda X: np.isclose(X[:, 2], 1.0)))
    flipped = f[:, [0, 3, 2, 1, 7, 6, 5, 4]]  # inward orientation, as a file may have it
    tags = [np.full(len(C), 1), np.full(len(f), 2)]
    path = tmp_path / "block.msh"
    meshio.Mesh(P, [("hexahedron20", C), ("quad8", flipped)],
                cell_data={"gmsh:physical": tags, "gmsh:geometrical": tags},
                field_data={"solid": np.array([1, 3]), "top": np.array([2, 2])}).write(
        path, file_format="gmsh22", binary=False)  # fmt: skip
    mesh, g = read_mesh(path)
    top = g.facet_group(mesh, "top")
    assert top.shape == (4, 8) and np.isclose(facet_area(mesh, top), 4.0)
    assert np.all(_mean_normals(mesh, top)[:, 2] > 0)
    np.testing.assert_array_equal(np.sort(top, 0), np.sort(f, 0))
    np.testing.assert_allclose(np.asarray(pressure_load(mesh, top, 1.0)).sum(0), [0, 0, -4.0],
                               atol=1e-12)  # fmt: skip


# --------------------------------------------------------------------------- abaqus


@pytest.mark.parametrize("name", ["LShapeH1.inp", "LShapeH1Medium.inp",
                                  "LShapeH2SerendipityCoarse.inp"])  # fmt: skip
def test_abaqus_surfaces_of_real_files(name):
    """moofeKIT's files load the top (y = 10) and the end (x = 6) of the L-block via
    `*SURFACE` S2 and S4 of element sets: checks the Abaqus face numbering."""
    mesh, g = read_mesh(DATA / name)
    for surface, axis, value in (("Surf-1", 1, 10.0), ("surf-2", 0, 6.0)):
        f = g.facet_group(mesh, surface)
        assert np.allclose(np.asarray(mesh.points)[f][..., axis], value)
        assert np.isclose(facet_area(mesh, f), 9.0)
        assert np.all(_mean_normals(mesh, f)[:, axis] > 0)
    assert g.names()["cells"] == ["_Surf-1_S2", "_Surf-2_S4"]


ABAQUS_HEX = [(0, 1, 2, 3), (4, 7, 6, 5), (0, 4, 5, 1), (1, 5, 6, 2), (2, 6, 7, 3), (3, 7, 4, 0)]


def test_abaqus_sets_and_surfaces(tmp_path):
    path = tmp_path / "lblock.inp"
    shutil.copy(DATA / "LShapeH1Medium.inp", path)
    text = path.read_text()
    node_lines = text.split("*Node")[1].split("*")[0].split("\n")[1:-1]
    labels_xyz = np.loadtxt(node_lines, delimiter=",")
    elem_lines = text.split("*Element, type=C3D8R")[1].split("*")[0].split("\n")[1:-1]
    elements = np.loadtxt(elem_lines, delimiter=",", dtype=int)
    X = labels_xyz[:, 1:]
    label_of = labels_xyz[:, 0].astype(int)
    bottom = label_of[np.isclose(X[:, 1], 0.0)]
    # Element faces on y = 0, found with the Abaqus face table (1-based in the manual).
    xyz = dict(zip(label_of, X))
    on = [(e[0], k + 1) for e in elements for k, face in enumerate(ABAQUS_HEX)
          if all(np.isclose(xyz[e[1 + i]][1], 0.0) for i in face)]
    assert len(on) == 18
    upper = elements[:, 0][[np.mean([xyz[n][1] for n in e[1:]]) > 5 for e in elements]]
    lines = ["*Nset, nset=Clamp, instance=Part-1-1"]
    lines += [", ".join(map(str, bottom[i : i + 8])) for i in range(0, len(bottom), 8)]
    lines += ["*Elset, elset=Upper, instance=Part-1-1"]
    lines += [", ".join(map(str, upper[i : i + 8])) for i in range(0, len(upper), 8)]
    lines += ["*Elset, elset=BOT_A, instance=Part-1-1"]
    lines += [f"{e}," for e, k in on[:9]]
    lines += ["*SURFACE, TYPE=ELEMENT,", "   NAME=Bottom"]  # a continued keyword line
    lines += [f"bot_a, S{on[0][1]}"] + [f"{e}, S{k}" for e, k in on[9:]]
    lines += ["*Surface, name=Broken", "Upper, S7", "*Surface, name=Inner, type=ELEMENT",
              f"{upper[0]}, S1", f"{upper[0]}, S2", f"{upper[0]}, S3", f"{upper[0]}, S4",
              f"{upper[0]}, S5", f"{upper[0]}, S6"]  # fmt: skip
    path.write_text(text + "\n".join(lines) + "\n")
    assert all(k == on[0][1] for _, k in on[:9])  # the elset line uses one face id
    mesh, g = read_mesh(path)
    P = np.asarray(mesh.points)
    np.testing.assert_array_equal(g.node_group("clamp"), np.flatnonzero(np.isclose(P[:, 1], 0)))
    cells = g.cell_group("UPPER")
    assert len(cells) == len(upper) and np.all(P[np.asarray(mesh.cells)[cells]].mean(1)[:, 1] > 5)
    f = g.facet_group(mesh, "bottom")
    assert f.shape == (18, 4) and np.isclose(facet_area(mesh, f), 18.0)
    np.testing.assert_array_equal(np.sort(f, 0), np.sort(facets_from_nodes(mesh, g.node_group(
        "clamp")), 0))  # fmt: skip
    assert np.all(_mean_normals(mesh, f)[:, 1] < 0)
    np.testing.assert_array_equal(g.node_group("Bottom"), g.node_group("clamp"))  # implied
    with pytest.raises(ValueError, match="facet group 'Broken' could not be read: face 'S7'"):
        g.facet_group(mesh, "broken")
    with pytest.raises(ValueError, match=r"'Inner' has \d of its 6 facets off the boundary"):
        g.facet_group(mesh, "Inner")
    with pytest.raises(ValueError, match=r"has no cell group 'lower'; node groups: \["):
        g.cell_group("lower")


def test_read_mesh_without_groups_and_other_formats(tmp_path):
    m = lshape_mesh(2, 1, "tri6")
    m.write(tmp_path / "l.vtu")
    mesh, g = read_mesh(tmp_path / "l.vtu")
    assert g.names() == {"nodes": [], "cells": [], "facets": []}
    with pytest.raises(ValueError, match="has no facet group 'x'; it has no named groups"):
        g.facet_group(mesh, "x")


def test_abaqus_labels_out_of_order_and_free_faces(tmp_path):
    """Node and element labels that are neither 0/1-based nor sorted, an unused node,
    a surface by element label, and a surface without face ids (the free faces)."""
    m = box(2, 1, 1, cell_type="hex8")
    P, C = np.asarray(m.points), np.asarray(m.cells)
    label = 500 - 7 * np.arange(len(P))
    left = np.isclose(P[:, 0], 0.0)
    face = next(k for k, fc in enumerate(ABAQUS_HEX) if left[C[0][list(fc)]].all())
    text = ["*Heading", "*Node", "1, 9., 9., 9."]
    text += [f"{lab}, {x}, {y}, {z}" for lab, (x, y, z) in zip(label, P)]
    text += ["*Element, type=C3D8"] + [f"{e}, " + ", ".join(map(str, label[c]))
                                       for e, c in zip((20, 10), C)]  # fmt: skip
    text += ["*Nset, nset=Left", ", ".join(map(str, label[left]))]
    text += ["*Surface, type=ELEMENT, name=LeftFace", f"20, S{face + 1}"]
    text += ["*Surface, name=Free", "20,"]
    path = tmp_path / "two.inp"
    path.write_text("\n".join(text) + "\n")
    mesh, g = read_mesh(path)
    np.testing.assert_array_equal(np.asarray(mesh.points), P)  # unused node 1 pruned
    np.testing.assert_array_equal(g.node_group("left"), np.flatnonzero(left))
    np.testing.assert_array_equal(g.facet_group(mesh, "leftface"),
                                  facets_from_nodes(mesh, np.flatnonzero(left)))  # fmt: skip
    free = g.facet_group(mesh, "FREE")
    assert len(free) == 5 and np.isclose(facet_area(mesh, free), 1.0 + 4 * 0.5)
    assert np.all(np.asarray(pressure_load(mesh, free, 1.0)).sum(0) == pytest.approx(
        [1.0, 0.0, 0.0]))  # fmt: skip
