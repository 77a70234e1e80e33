"""Write the meshes of the example scene files (their output is committed beside them).

    python examples/scenes/make_meshes.py

- ``beam2d.msh`` (Gmsh 2.2): a 4 x 1 strip of 16 x 4 quad4 cells with the physical groups
  ``beam`` (the cells) and ``left``, ``right``, ``bottom``, ``top`` (boundary lines).
- ``block3d.inp`` (Abaqus): a 2 x 1 x 1 block of 6 x 3 x 3 hex8 cells with ``*NSET``
  ``CLAMP`` (the nodes on x = 0), ``*ELSET`` ``BLOCK`` (all cells) and ``END`` (the cells
  at x = 2), and ``*SURFACE`` ``LOADED`` (the faces of ``END`` on x = 2).
"""

import os

import meshio
import numpy as np

import jaxvisco as jv

HERE = os.path.dirname(os.path.abspath(__file__))


def beam2d(path, nx=16, ny=4, lx=4.0, ly=1.0):
    mesh = jv.rectangle(nx, ny, lx, ly, cell_type="quad4")
    X = np.asarray(mesh.points)
    edges = jv.boundary_facets(mesh)
    sides = {"left": (0, 0.0), "right": (0, lx), "bottom": (1, 0.0), "top": (1, ly)}
    cells = [("quad", np.asarray(mesh.cells))]
    physical = [np.full(mesh.n_cells, 1)]
    field_data = {"beam": np.array([1, 2])}
    for tag, (name, (axis, value)) in enumerate(sides.items(), start=2):
        on = np.all(np.isclose(X[edges, axis], value), axis=1)
        cells.append(("line", edges[on]))
        physical.append(np.full(np.count_nonzero(on), tag))
        field_data[name] = np.array([tag, 1])
    points = np.column_stack([X, np.zeros(len(X))])
    meshio.write(path, meshio.Mesh(points, cells, cell_data={"gmsh:physical": physical, "gmsh:geometrical": physical},
                                   field_data=field_data), file_format="gmsh22", binary=False)


def _lines(labels, per_line=16):
    labels = [str(int(a)) for a in labels]
    return [", ".join(labels[i:i + per_line]) for i in range(0, len(labels), per_line)]


def block3d(path, n=(6, 3, 3), lengths=(2.0, 1.0, 1.0)):
    mesh = jv.box(*n, *lengths, cell_type="hex8")
    X, cells = np.asarray(mesh.points), np.asarray(mesh.cells)
    faces = jv.local_facets("hex8")  # row k is Abaqus face S{k+1}
    out = ["*HEADING", "jaxvisco example: 2 x 1 x 1 block, clamped at x = 0, pressure on x = 2", "*NODE"]
    out += [f"{i + 1}, {x:.17g}, {y:.17g}, {z:.17g}" for i, (x, y, z) in enumerate(X)]
    out.append("*ELEMENT, TYPE=C3D8, ELSET=BLOCK")
    out += [f"{e + 1}, " + ", ".join(str(a + 1) for a in c) for e, c in enumerate(cells)]
    out.append("*NSET, NSET=CLAMP")
    out += _lines(np.flatnonzero(np.isclose(X[:, 0], 0.0)) + 1)
    on_end = np.isclose(X[cells[:, faces], 0], lengths[0]).all(axis=2)  # (n_cells, 6): face on x = lx
    end_cells, end_faces = np.nonzero(on_end)
    out.append("*ELSET, ELSET=END")
    out += _lines(end_cells + 1)
    assert len(set(end_faces)) == 1
    out += ["*SURFACE, NAME=LOADED, TYPE=ELEMENT", f"END, S{end_faces[0] + 1}"]
    with open(path, "w") as f:
        f.write("\n".join(out) + "\n")


if __name__ == "__main__":
    import jax

    jax.config.update("jax_enable_x64", True)
    beam2d(os.path.join(HERE, "beam2d.msh"))
    block3d(os.path.join(HERE, "block3d.inp"))
    print(f"wrote beam2d.msh and block3d.inp in {HERE}")
