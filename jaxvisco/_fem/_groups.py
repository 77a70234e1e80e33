"""Named node, cell and facet groups read from mesh files.

- Gmsh (.msh 2.2 and 4.1): named physical groups. Groups of the mesh's dimension are cell
  groups, one dimension lower facet groups, lower still (points; curves in 3D) node
  groups. Unnamed physical groups are ignored.
- Abaqus (.inp): `*NSET` node groups, `*ELSET` cell groups and `*SURFACE, TYPE=ELEMENT`
  facet groups (element or element-set, face `S1`..`S6`; without a face, the boundary
  facets of those elements). Names are looked up case-insensitively, as in Abaqus.
- Other formats: meshio's `point_sets` and `cell_sets`, if any.

Every cell or facet group also gives a node group of the same name (its nodes) unless the
file has a node group of that name. Facets are outward oriented as `boundary_facets`
returns them: a file's facets are matched to the mesh's boundary facets by their corners.
"""

import dataclasses
import os
import re
import warnings

import numpy as np

from ._boundary import _boundary, facets_from_nodes, local_facets, match_boundary
from ._mesh import _MESHIO_DIM, Mesh


@dataclasses.dataclass(frozen=True, eq=False)
class MeshGroups:
    """Named groups of a mesh file (host-side numpy; never traced by JAX).

    **Fields:**

    - `nodes`: name -> sorted unique node indices (numbering of `Mesh.read`).
    - `cells`: name -> sorted indices into `mesh.cells`.
    - `facets`: name -> outward facets `(n, n_facet_nodes)`, as `boundary_facets` gives.
    - `source`: file name, for messages.
    - `case_insensitive`: look names up ignoring case (Abaqus files).
    - `problems`: `(kind, name)` -> why a group the file names could not be built (e.g.
      a surface of interior faces); raised when that group is asked for.
    """

    nodes: dict = dataclasses.field(default_factory=dict)
    cells: dict = dataclasses.field(default_factory=dict)
    facets: dict = dataclasses.field(default_factory=dict)
    source: str = "mesh"
    case_insensitive: bool = False
    problems: dict = dataclasses.field(default_factory=dict)

    def names(self) -> dict:
        """`{"nodes": [...], "cells": [...], "facets": [...]}`, sorted names per kind."""
        return {k: sorted(getattr(self, k)) for k in ("nodes", "cells", "facets")}

    def __repr__(self):
        parts = ", ".join(f"{k}={v}" for k, v in self.names().items())
        return f"MeshGroups({self.source!r}: {parts})"

    def _find(self, kind, name):
        groups = getattr(self, kind)
        if name in groups:
            return name
        if self.case_insensitive and isinstance(name, str):
            hits = [k for k in groups if k.casefold() == name.casefold()]
            if len(hits) > 1:
                raise ValueError(
                    f"mesh {self.source!r}: {kind[:-1]} group name {name!r} is ambiguous "
                    f"(case-insensitive): {sorted(hits)}."
                )
            if hits:
                return hits[0]
        return None

    def _problem(self, kind, name):
        """`(name as written, reason)` if the file names group `name` but it failed."""
        for (k, n), why in self.problems.items():
            same = n.casefold() == str(name).casefold() if self.case_insensitive else n == name
            if k == kind and same:
                return n, why
        return None

    def _missing(self, kind, name):
        failed = self._problem(kind[:-1], name)
        if failed is not None:
            return ValueError(f"mesh {self.source!r}: {kind[:-1]} group {failed[0]!r} "
                              f"{failed[1]}")
        listing = "; ".join(f"{k[:-1]} groups: {v}" for k, v in self.names().items() if v)
        return ValueError(
            f"mesh {self.source!r} has no {kind[:-1]} group {name!r}; "
            + (listing or "it has no named groups") + "."
        )

    def node_group(self, name) -> np.ndarray:
        """Sorted node indices of group `name`; `ValueError` listing the groups if absent."""
        key = self._find("nodes", name)
        if key is None:
            raise self._missing("nodes", name)
        return self.nodes[key]

    def cell_group(self, name) -> np.ndarray:
        """Cell indices of group `name`; `ValueError` listing the groups if absent."""
        key = self._find("cells", name)
        if key is None:
            raise self._missing("cells", name)
        return self.cells[key]

    def facet_group(self, mesh, name) -> np.ndarray:
        """Outward facets of group `name`.

        The file's facet group of that name if there is one; else the boundary facets
        whose nodes all lie in the node group of that name (`facets_from_nodes`).

        **Arguments:**

        - `mesh`: the `Mesh` the groups were read with.
        - `name`: group name.

        **Returns:**

        int64 `(n_facets, n_facet_nodes)`. Raises `ValueError` naming the groups the
        mesh has if neither a facet nor a node group `name` exists.
        """
        key = self._find("facets", name)
        if key is not None:
            return self.facets[key]
        if self._problem("facet", name) is not None:
            raise self._missing("facets", name)
        key = self._find("nodes", name)
        if key is None:
            raise self._missing("facets", name)
        try:
            return facets_from_nodes(mesh, self.nodes[key])
        except ValueError as e:
            raise ValueError(
                f"mesh {self.source!r}: node group {key!r} ({len(self.nodes[key])} nodes) "
                f"holds no boundary facet: {e}"
            ) from None


# --------------------------------------------------------------------------- reading


def _merge(groups, name, values):
    groups.setdefault(name, []).append(values)


def _inp_records(path):
    """Keyword records `(KEYWORD, {PARAM: value}, data lines)` of an Abaqus input file.

    Keywords are upper-cased without spaces, parameter names upper-cased, values kept as
    written; `**` comments and blank lines are skipped; a keyword line ending in a comma
    continues on the next line.
    """
    with open(path, errors="replace") as f:
        lines = [ln.strip() for ln in f.read().splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("**")]
    records, i = [], 0
    while i < len(lines):
        line, i = lines[i], i + 1
        if not line.startswith("*"):
            continue
        while line.endswith(",") and i < len(lines) and not lines[i].startswith("*"):
            line, i = line + lines[i], i + 1
        words = [w.strip() for w in line[1:].split(",")]
        params = {}
        for word in words[1:]:
            key, _, value = word.partition("=")
            if key.strip():
                params[key.strip().upper()] = value.strip()
        start = i
        while i < len(lines) and not lines[i].startswith("*"):
            i += 1
        records.append((words[0].upper().replace(" ", ""), params, lines[start:i]))
    return records


def _abaqus_surfaces(path, m, offsets, mesh):
    """`*SURFACE, TYPE=ELEMENT` sets: name -> (cell indices, local facet or -1 = free)."""
    records = _inp_records(path)
    # Element labels in mesh.cells order; meshio makes one block per *ELEMENT keyword.
    labels = np.full(mesh.n_cells, -1, dtype=np.int64)
    elements = [data for key, _, data in records if key == "ELEMENT"]
    if len(elements) == len(m.cells):
        for b, start in offsets.items():
            tokens = [t for t in re.split(r"[,\s]+", " ".join(elements[b])) if t]
            ints = np.asarray(tokens).astype(np.int64)
            n = len(m.cells[b].data)
            if ints.size == n * (m.cells[b].data.shape[1] + 1):
                labels[start : start + n] = ints.reshape(n, -1)[:, 0]
    order = np.argsort(labels)
    elsets = {k.casefold(): v for k, v in m.cell_sets.items()}
    n_local = local_facets(mesh.cell_type).shape[0]
    out, problems = {}, {}
    for keyword, params, data in records:
        if keyword != "SURFACE" or "NAME" not in params:
            continue
        name, kind = params["NAME"], params.get("TYPE", "ELEMENT").upper()
        if kind != "ELEMENT":
            problems[name] = f"is a *SURFACE of TYPE={kind}; only TYPE=ELEMENT is read."
            continue
        cells, faces, numbers, number_faces = [], [], [], []
        try:
            for line in data:
                ref, face = [t.strip() for t in (line + ",").split(",")][:2]
                face = face.upper()
                if re.fullmatch(r"S\d+", face) and 1 <= int(face[1:]) <= n_local:
                    k = int(face[1:]) - 1
                elif face == "":
                    k = -1  # no face: the free faces of the elements
                else:
                    raise LookupError(f"face {face!r} in line {line!r} is not one of "
                                      f"S1..S{n_local} of {mesh.cell_type} cells.")
                if re.fullmatch(r"-?\d+", ref):
                    numbers.append(int(ref))
                    number_faces.append(k)
                elif ref.casefold() in elsets:
                    c = [np.asarray(s, dtype=np.int64) + offsets[b] for b, s
                         in enumerate(elsets[ref.casefold()]) if b in offsets]
                    cells.append(np.concatenate(c + [np.zeros(0, np.int64)]))
                    faces.append(np.full(len(cells[-1]), k))
                else:
                    raise LookupError(f"element set {ref!r} is not defined.")
            numbers = np.asarray(numbers, dtype=np.int64)
            pos = np.searchsorted(labels, numbers, sorter=order).clip(0, len(labels) - 1)
            found = labels[order[pos]] == numbers
            if not found.all():
                raise LookupError(f"element {numbers[~found][0]} is not one of the "
                                  f"{mesh.cell_type} cells read.")
        except LookupError as e:
            problems[name] = f"could not be read: {e.args[0]}"
            continue
        cells.append(order[pos])
        faces.append(np.asarray(number_faces, dtype=np.int64))
        out.setdefault(name, []).append((np.concatenate(cells), np.concatenate(faces)))
    out = {k: tuple(np.concatenate(x) for x in zip(*v)) for k, v in out.items()}
    return out, problems


def read_mesh(path: str | os.PathLike, cell_type: str | None = None) -> tuple[Mesh, MeshGroups]:
    """Read a mesh file and its named groups.

    **Arguments:**

    - `path`: mesh file (.msh, .inp, .vtu, .xdmf... anything meshio reads).
    - `cell_type`: as in `Mesh.read`.

    **Returns:**

    `(mesh, groups)`: the `Mesh` exactly as `Mesh.read(path, cell_type)` returns it and
    a `MeshGroups` in its node and cell numbering.
    """
    import meshio

    mesh = Mesh.read(path, cell_type)
    path = os.fspath(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = meshio.read(path)
    ctype = mesh.element.meshio_name
    kept = [b for b, block in enumerate(m.cells) if block.type == ctype and len(block.data)]
    offsets, n = {}, 0
    for b in kept:
        offsets[b], n = n, n + len(m.cells[b].data)
    used = np.unique(np.concatenate([m.cells[b].data for b in kept]).ravel())

    def renumber(old):
        old = np.asarray(old, dtype=np.int64)
        new = np.clip(np.searchsorted(used, old), 0, len(used) - 1)
        return new, used[new] == old

    check, _ = renumber(np.concatenate([m.cells[b].data for b in kept]))
    if not np.array_equal(check.reshape(mesh.cells.shape), np.asarray(mesh.cells)):
        raise RuntimeError(f"node numbering of {path!r} differs from Mesh.read's.")

    # Sets as meshio gives them: name -> one index array per cell block.
    sets = {k: v for k, v in m.cell_sets.items() if not k.startswith("gmsh:")}
    phys = m.cell_data.get("gmsh:physical")
    if phys is not None and len(phys) == len(m.cells):
        for name, (tag, dim) in m.field_data.items():
            if name not in sets:
                sets[name] = [np.flatnonzero((np.asarray(t) == tag) & (
                    _MESHIO_DIM.get(block.type, -1) == dim)) for t, block in zip(phys, m.cells)]
    top = mesh.element.dim
    nodes, cells, facets, problems = {}, {}, {}, {}
    for name, per_block in sets.items():
        for b, idx in zip(range(len(m.cells)), per_block):
            idx = np.asarray(idx, dtype=np.int64).ravel()
            if not idx.size:
                continue
            block, dim = m.cells[b], _MESHIO_DIM.get(m.cells[b].type, -1)
            if b in offsets:
                _merge(cells, name, offsets[b] + idx)
            elif dim == top - 1:
                _merge(facets, name, block.data[idx])
            elif 0 <= dim < top - 1:
                _merge(nodes, name, block.data[idx].ravel())
    # Raw sets in the file's numbering -> the mesh's numbering.
    nodes = {k: np.concatenate(v) for k, v in nodes.items()}
    for name, idx in m.point_sets.items():
        nodes[name] = np.concatenate([nodes.get(name, []), np.asarray(idx).ravel()])
    for name in list(nodes):
        new, ok = renumber(nodes[name])
        if not ok.any():
            problems[("node", name)] = "has no node that belongs to a cell of the mesh."
            del nodes[name]
            continue
        nodes[name] = np.unique(new[ok])
    cells = {k: np.unique(np.concatenate(v)) for k, v in cells.items()}
    for name, raw in list(facets.items()):
        raws = [renumber(r) for r in raw]
        if not all(ok.all() for _, ok in raws):
            problems[("facet", name)] = "has nodes that belong to no cell of the mesh."
            del facets[name]
            continue
        rows = np.concatenate([r[:, : min(x.shape[1] for x, _ in raws)] for r, _ in raws])
        facets[name] = _oriented(mesh, name, rows, problems)
    inp = path.lower().endswith(".inp")
    if inp:
        surfaces, bad = _abaqus_surfaces(path, m, offsets, mesh)
        problems.update({("facet", k): v for k, v in bad.items()})
        table = local_facets(mesh.cell_type)
        all_facets = np.asarray(mesh.cells, dtype=np.int64)[:, table]
        free = np.zeros((mesh.n_cells, len(table)), dtype=bool)
        _, owner, local = _boundary(mesh)
        free[owner, local] = True
        for name, (c, k) in surfaces.items():
            chosen = np.where(k[:, None] < 0, free[c], np.arange(len(table)) == k[:, None])
            facets[name] = _oriented(mesh, name, all_facets[c][chosen], problems)
    facets = {k: v for k, v in facets.items() if v is not None}
    # Facet and cell groups imply node groups of the same name.
    implied = [(k, v) for k, v in facets.items()]
    implied += [(k, np.asarray(mesh.cells)[v]) for k, v in cells.items()]
    for name, conn in implied:
        fold = {k.casefold() if inp else k for k in nodes}
        if (name.casefold() if inp else name) not in fold:
            nodes[name] = np.unique(conn).astype(np.int64)
    groups = MeshGroups(nodes=nodes, cells=cells, facets=facets,
                        source=os.path.basename(path), case_insensitive=inp,
                        problems=problems)  # fmt: skip
    return mesh, groups


def _oriented(mesh, name, rows, problems):
    """Outward boundary facets matching `rows`, or None (and a problem) if some are not."""
    if not len(rows):
        problems[("facet", name)] = "is empty."
        return None
    out, found = match_boundary(mesh, rows)
    if not found.all():
        problems[("facet", name)] = (
            f"has {np.count_nonzero(~found)} of its {len(rows)} facets off the boundary "
            "of the mesh (interior faces, or faces of other cells); a load surface must "
            "lie on the boundary."
        )
        return None
    return out
