"""Scene files: a run described in TOML (``jaxvisco run SCENE.toml``, `read_scene_file`).

Tables and their keys (``jaxvisco scene-template`` prints a commented, runnable file that
documents each one; paths are relative to the scene file):

- ``[mesh]``: ``file`` (any meshio format) or ``generator`` (``"rectangle"``: nx, ny, lx,
  ly, origin; ``"box"``: nx, ny, nz, lx, ly, lz, origin; ``"lshape"``: dim, refinement),
  ``cell_type``, ``quadrature_order``.
- ``[groups.NAME]``: node groups by coordinate ranges ``x``, ``y``, ``z`` (``[lo, hi]``
  or a number), beside the mesh file's groups (Gmsh physical groups, Abaqus sets).
- ``[material]``: ``lam``, ``mu``, ``eta_dev``, ``eta_vol`` (or ``[material.equilibrium]``
  and ``[material.nonequilibrium]`` with ``lam``, ``mu``), ``density``, ``mass``;
  ``[[material.part]]``: ``cells`` (cell groups) and any of those material keys,
  ``density`` included.
- ``[initial]``: ``velocity``, ``angular_velocity``, ``center``, ``[[initial.velocity_field]]``
  (``nodes``, ``value``).
- ``[[dirichlet]]``: ``nodes``, ``components``, ``displacement``, ``time``.
- ``[[load]]``: ``nodes``, ``force`` (on each node), ``time``.
- ``[[traction]]``: ``facets``, ``traction`` or ``pressure``, ``time``.
- ``[integrator]``: ``name``, ``order``, ``quadrature``; ``[solver]``: `NewtonKrylov`'s
  keywords, ``[solver.gmres]``: `GMRES`'s.
- ``[time]``: ``t0``, ``t1``, ``dt0`` or ``schedule``, ``max_halvings``; or
  ``rtol``/``atol`` (error-controlled steps; ``dt0`` the first step tried).
- ``[saveat]``: ``every``, ``gamma``; ``[output]``: ``file``, ``chunk``, ``commit_every``.

The names of jaxvisco 0.1 (``[time]`` ``t_end``, ``dt``; ``[output]`` ``save_every``,
``save_gamma``; ``[solver]`` ``krylov``, ``krylov_max_steps``, ``refresh_after``,
``preconditioner``, ``restart``, ``multigrid_precision``) are deprecated aliases
(`_scenerun`).

A time function is a table ``{ type = "step", at = 1.0, ... }`` of a small fixed set
(`_time_functions`); no user text is ever evaluated. The whole file is checked before
anything runs: an unknown table or key, a missing key, a wrong type or value, a group the
mesh lacks, a component out of range each raise one `ValueError` whose message names the
file, the table and key, the bad value and what is accepted, e.g.
``beam.toml: [[load]] 2: nodes: no node group 'tipp'; ...``.
"""

import math
import os
import warnings
from typing import Optional

import numpy as np

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from ._result import SceneFile as SceneFile
from ._scenematerial import MaterialReader as _MaterialReader
from ._scenerun import RunReader as _RunReader
from ._scenetable import Table as _Table
from ._scenetemplate import TEMPLATE as TEMPLATE

_TABLES = ("mesh", "groups", "material", "initial", "dirichlet", "load", "traction", "integrator", "solver", "time",
           "saveat", "output")
_ARRAYS = ("dirichlet", "load", "traction")
_GENERATOR_KEYS = {"rectangle": ("nx", "ny", "lx", "ly", "origin"),
                   "box": ("nx", "ny", "nz", "lx", "ly", "lz", "origin"), "lshape": ("dim", "refinement")}
_AXES = "xyz"


class _Reader(_MaterialReader, _RunReader):
    """Reads one parsed scene file into a `SceneFile`."""

    def __init__(self, name, doc, base_dir):
        self.name, self.doc, self.base_dir = name, doc, base_dir
        self.notes = []  # deprecated names used (`SceneFile.deprecated`)
        for key, value in doc.items():
            if key not in _TABLES:
                raise ValueError(f"{name}: unknown table [{key}]; accepted: "
                                 f"{', '.join(f'[[{t}]]' if t in _ARRAYS else f'[{t}]' for t in _TABLES)}.")
            if key in _ARRAYS and not (isinstance(value, list) and all(isinstance(e, dict) for e in value)):
                raise ValueError(f"{name}: [{key}] must be an array of tables: write [[{key}]] (one per entry).")

    def table(self, key, accepted, required=True, aliases=None):
        if key not in self.doc and not required:
            return _Table(self.name, {}, f"[{key}]", accepted, aliases)
        if key not in self.doc:
            raise ValueError(f"{self.name}: [{key}]: missing (required).")
        return _Table(self.name, self.doc[key], f"[{key}]", accepted, aliases)

    def entries(self, key, accepted):
        return [_Table(self.name, e, f"[[{key}]] {i}", accepted) for i, e in enumerate(self.doc.get(key, []), 1)]

    # ------------------------------------------------------------------ mesh and groups
    def mesh_and_groups(self):
        from .._fem._generators import box, lshape_mesh, rectangle
        from .._fem._groups import MeshGroups, read_mesh

        data = self.doc.get("mesh")
        gen = data.get("generator") if isinstance(data, dict) else None
        if gen is not None:
            _Table(self.name, {"generator": gen}, "[mesh]", ("generator",)).string("generator",
                                                                                 choices=tuple(_GENERATOR_KEYS))
        t = self.table("mesh", ("file", "generator", *_GENERATOR_KEYS.get(gen, ()), "cell_type", "quadrature_order"))
        if t.has("file") == t.has("generator"):
            raise t.error("file", "give either file = \"MESH\" (a mesh file) or generator = \"rectangle\" | \"box\" | "
                          "\"lshape\", not both" if t.has("file") else "missing: give file = \"MESH\" or "
                          "generator = \"rectangle\" | \"box\" | \"lshape\".")
        cell_type = t.string("cell_type", None)
        self.quadrature_order = t.integer("quadrature_order", None, minimum=1)
        if t.has("file"):
            path = os.path.join(self.base_dir, t.string("file"))
            try:
                return read_mesh(path, cell_type=cell_type)
            except (ValueError, OSError) as e:
                raise t.error("file", " ".join(str(e).split())) from None
        gen = t.string("generator", choices=tuple(_GENERATOR_KEYS))
        try:
            if gen == "lshape":
                mesh = lshape_mesh(dim=t.integer("dim", 2, minimum=2, maximum=3),
                                   refinement=t.integer("refinement", 1, minimum=1), cell_type=cell_type)
            else:
                dim = 2 if gen == "rectangle" else 3
                counts = [t.integer(k, minimum=1) for k in ("nx", "ny", "nz")[:dim]]
                lengths = [t.number(k, 1.0, positive=True) for k in ("lx", "ly", "lz")[:dim]]
                kw = dict(origin=t.vector("origin", dim, np.zeros(dim)))
                if cell_type is not None:
                    kw["cell_type"] = cell_type
                mesh = (rectangle if dim == 2 else box)(*counts, *lengths, **kw)
        except ValueError as e:
            if str(e).startswith(self.name):
                raise
            raise t.error("cell_type" if cell_type is not None else "generator", str(e)) from None
        return mesh, MeshGroups(source=gen)

    def coordinate_groups(self, mesh, groups):
        data = self.doc.get("groups", {})
        if not isinstance(data, dict):
            raise ValueError(f"{self.name}: [groups]: expected tables [groups.NAME], got {data!r}.")
        X = np.asarray(mesh.points)
        lo, hi = X.min(axis=0), X.max(axis=0)
        tol = 1e-9 * float(np.linalg.norm(hi - lo))
        out = {}
        for gname, spec in data.items():
            t = _Table(self.name, spec, f"[groups.{gname}]", tuple(_AXES))
            if _has_node_group(groups, gname):
                raise ValueError(f"{self.name}: [groups.{gname}]: the mesh file already has a node group {gname!r}; "
                                 "choose another name.")
            if not spec:
                raise t.error("x", "missing: give at least one coordinate range x, y or z.")
            keep = np.ones(len(X), dtype=bool)
            for axis, key in enumerate(_AXES):
                if not t.has(key):
                    continue
                if axis >= mesh.dim:
                    raise t.error(key, f"the mesh is {mesh.dim}D; accepted: {', '.join(_AXES[:mesh.dim])}.")
                v = t.raw(key)
                r = [v, v] if isinstance(v, (int, float)) and not isinstance(v, bool) else v
                rng = t.vector(key, 2, what="numbers [lo, hi] (or one number)") if r is v else np.asarray(r, float)
                if not (math.isfinite(rng[0]) and rng[0] <= rng[1]):
                    raise t.error(key, f"got {v!r}; accepted: a range [lo, hi] with lo <= hi, or one number.")
                keep &= (X[:, axis] >= rng[0] - tol) & (X[:, axis] <= rng[1] + tol)
            if not keep.any():
                extent = ", ".join(f"{_AXES[i]} in [{lo[i]:g}, {hi[i]:g}]" for i in range(mesh.dim))
                raise ValueError(f"{self.name}: [groups.{gname}]: selects no node; the mesh spans {extent}.")
            out[gname] = np.flatnonzero(keep)
        return out

    def _missing(self, t, key, gname, e):
        defined = f"[groups] defines: {', '.join(sorted(self.extra))}" if self.extra else "[groups] defines none"
        if not any(self.groups.names().values()) and gname not in self.extra:
            kind = {"facets": "facet or node", "cells": "cell"}.get(key, "node")
            return t.error(key, f"no {kind} group {gname!r}; the mesh has no named groups and {defined}.")
        return t.error(key, f"{' '.join(str(e).split()).rstrip('.')}; {defined}.")

    def node_group(self, gname):
        """The node indices of one group by name (`SceneFile.nodes`)."""
        if gname in self.extra:
            return np.asarray(self.extra[gname])
        try:
            return np.asarray(self.groups.node_group(gname))
        except ValueError:
            names = sorted(set(self.extra) | set(self.groups.names()["nodes"]))
            raise ValueError(f"{self.name}: no node group {gname!r}; the scene file has: "
                             f"{', '.join(names) if names else 'none'}.") from None

    def nodes(self, t, key="nodes"):
        """The node indices (sorted, unique) of the groups named by `t[key]`."""
        out = []
        for gname in t.names(key):
            try:
                out.append(self.extra[gname] if gname in self.extra else np.asarray(self.groups.node_group(gname)))
            except ValueError as e:
                raise self._missing(t, key, gname, e) from None
        return np.unique(np.concatenate(out))

    def facets(self, t, key="facets"):
        """The outward boundary facets of the groups named by `t[key]`: facet groups of
        the mesh file, or the boundary facets of node groups."""
        from .._fem._boundary import facets_from_nodes

        out = []
        for gname in t.names(key):
            try:
                if gname in self.extra:
                    out.append(np.asarray(facets_from_nodes(self.mesh, self.extra[gname])))
                else:
                    out.append(np.asarray(self.groups.facet_group(self.mesh, gname)))
            except ValueError as e:
                raise self._missing(t, key, gname, f"group {gname!r}: {e}" if gname in self.extra else e) from None
        return np.unique(np.concatenate(out), axis=0)

    def components(self, t, key="components"):
        dim = self.mesh.dim
        v = t.raw(key, "all")
        accepted = f"\"all\" or a list of {', '.join(repr(a) for a in _AXES[:dim])} (or 0..{dim - 1})"
        items = [v] if isinstance(v, str) and v != "all" else v
        if v == "all":
            return list(range(dim))
        out = []
        for a in items if isinstance(items, list) and items else [None]:
            c = _AXES.find(a) if isinstance(a, str) and len(a) == 1 else a
            if isinstance(c, bool) or not isinstance(c, int) or not 0 <= c < dim:
                raise t.error(key, f"got {a!r} in {v!r}; the mesh is {dim}D, accepted: {accepted}.")
            out.append(c)
        return sorted(set(out))

    def time_function(self, t, required=False):
        from .._time_functions import time_function_from_dict

        if not t.has("time"):
            if required:
                raise t.error("time", "missing: prescribed motion needs a time function g(t) with g(0) = 0.")
            return None
        return time_function_from_dict(t.raw("time"), f"{self.name}: {t.where}: time: ")

    # ------------------------------------------------------------------ the scene
    def scene(self):
        from .._fem._boundary import pressure_load, traction_load
        from .._scene import Scene

        self.mesh, self.groups = self.mesh_and_groups()
        dim, n = self.mesh.dim, self.mesh.n_nodes
        self.extra = self.coordinate_groups(self.mesh, self.groups)
        material, density, mass = self.read_material()
        v0 = self.initial_velocity()
        fixed = np.zeros((n, dim), dtype=bool)
        prescribed = []
        for t in self.entries("dirichlet", ("nodes", "components", "displacement", "time")):
            nodes, comps = self.nodes(t), self.components(t)
            fixed[np.ix_(nodes, comps)] = True
            if t.has("displacement"):
                u = t.vector("displacement", dim)
                off = [c for c in range(dim) if c not in comps and u[c] != 0]
                if off:
                    raise t.error("displacement", f"component {_AXES[off[0]]!r} is {float(u[off[0]])!r} but not held; "
                                  "entries of components not in `components` must be 0.")
                g = self.time_function(t, required=True)
                g0 = float(g(0.0))
                if g0 != 0.0:
                    raise t.error("time", f"g(0) = {g0!r}; prescribed motion must start at 0 (the held nodes start "
                                  "at their initial positions).")
                field = np.zeros((n, dim))
                field[nodes] = u
                prescribed.append((field, g))
            elif t.has("time"):
                raise t.error("time", "a time function needs a `displacement` to scale.")
        loads = []
        for t in self.entries("load", ("nodes", "force", "time")):
            nodes, force = self.nodes(t), t.vector("force", dim)
            f = np.zeros((n, dim))
            f[nodes] = force
            loads.append((f, self.time_function(t)))
        for t in self.entries("traction", ("facets", "traction", "pressure", "time")):
            if t.has("traction") == t.has("pressure"):
                raise t.error("traction", "give either traction = [...] (force per reference area) or pressure = p, "
                              "not both." if t.has("traction") else "missing: give traction = [...] or pressure = p.")
            facets = self.facets(t)
            if t.has("traction"):
                f = traction_load(self.mesh, facets, t.vector("traction", dim))
            else:
                f = pressure_load(self.mesh, facets, t.number("pressure"))
            loads.append((np.asarray(f), self.time_function(t)))
        try:
            return Scene(self.mesh, material, density, velocities=v0, fixed=fixed if fixed.any() else None,
                         mass=mass, quadrature_order=self.quadrature_order, loads=loads or None,
                         prescribed=prescribed or None)
        except (ValueError, TypeError) as e:
            raise ValueError(f"{self.name}: {' '.join(str(e).split())}") from None

    def initial_velocity(self):
        t = self.table("initial", ("velocity", "angular_velocity", "center", "velocity_field"), required=False)
        from .._fem._rigid import rigid_velocity

        dim = self.mesh.dim
        if t.has("center") and not t.has("angular_velocity"):
            raise t.error("center", "a center needs an angular_velocity.")
        w = None
        if t.has("angular_velocity"):
            w = t.number("angular_velocity") if dim == 2 else t.vector("angular_velocity", 3)
        v = np.array(rigid_velocity(self.mesh, velocity=t.vector("velocity", dim, np.zeros(dim)), angular_velocity=w,
                                    center=t.vector("center", dim, None) if t.has("center") else None))
        fields = t.raw("velocity_field", [])
        if not (isinstance(fields, list) and all(isinstance(e, dict) for e in fields)):
            raise t.error("velocity_field", "write it as an array of tables [[initial.velocity_field]].")
        for i, e in enumerate(fields, 1):
            ft = _Table(self.name, e, f"[[initial.velocity_field]] {i}", ("nodes", "value"))
            v[self.nodes(ft)] = ft.vector("value", dim)
        return v


def _has_node_group(groups, name):
    try:
        groups.node_group(name)
    except ValueError:
        return False
    return True


def read_scene_file(path: str | os.PathLike, *, source: Optional[str] = None, base_dir: Optional[str] = None
                    ) -> SceneFile:
    """Read and check a scene file (TOML): the scene and its run settings.

    The format is described in the user guide's scene-file page, and
    `jaxvisco scene-template` prints a commented file with every table and key. Keys
    of jaxvisco 0.1 (`t_end`, `dt`, `save_every`, ...) are read with a `FutureWarning`
    naming their replacements.

    **Arguments:**

    - `path`: the `.toml` file (its name starts every error message).
    - `source`: the file's text, to read a stored copy instead of `path`.
    - `base_dir`: where relative paths start (default: the folder of `path`).

    **Returns:**

    A `SceneFile`.

    **Raises:**

    `ValueError` (one line: file, table, key, bad value and what is accepted) for
    anything wrong in the file; `FileNotFoundError` if `path` does not exist.
    """
    sf = read_quietly(path, source=source, base_dir=base_dir)
    for note in sf.deprecated:
        warnings.warn(note + ".", FutureWarning, stacklevel=2)
    return sf


def read_quietly(path, source=None, base_dir=None) -> SceneFile:
    """`read_scene_file` without its warnings (the command line prints the notes of
    `SceneFile.deprecated` itself)."""
    name = os.fspath(path)
    if source is None:
        if not os.path.isfile(name):
            raise FileNotFoundError(f"scene file {name!r} does not exist.")
        with open(name, encoding="utf-8") as f:
            source = f.read()
    if base_dir is None:
        base_dir = os.path.dirname(os.path.abspath(name))
    try:
        doc = tomllib.loads(source)
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{name}: not valid TOML: {e}") from None
    r = _Reader(name, doc, os.fspath(base_dir))
    options = r.run_options()
    return SceneFile(scene=r.scene(), source=source, path=name, base_dir=r.base_dir, deprecated=tuple(r.notes),
                     node_groups=r.node_group, **options)


def scene_from_file(path):
    """The `Scene` that the scene file `path` describes (`read_scene_file(path).scene`)."""
    return read_scene_file(path).scene
