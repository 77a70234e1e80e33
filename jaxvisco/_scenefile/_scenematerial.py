"""The ``[material]`` table of a scene file (`_scenefile`): Neo-Hooke branches,
viscosities and density, one material for the body or one per part
(``[[material.part]]``, a cell group with its own data, density included)."""

import math

import numpy as np

from ._scenetable import Table as _Table

_MATERIAL_KEYS = ("lam", "mu", "eta_dev", "eta_vol", "equilibrium", "nonequilibrium")


class MaterialReader:
    """The material methods of `_scenefile._Reader` (which provides `name`, `mesh`,
    `groups`, `extra`, `table` and `_missing`)."""

    def read_material(self):
        """`(material, density, mass)`; the material is a list of `(material, cells)`
        pairs where ``[[material.part]]`` entries give cell groups their own data."""
        t = self.table("material", _MATERIAL_KEYS + ("density", "mass", "part"))
        density = t.number("density", positive=True)
        mass = t.string("mass", "consistent", choices=("consistent", "lumped"))
        parts = t.raw("part", [])
        if not (isinstance(parts, list) and all(isinstance(p, dict) for p in parts)):
            raise t.error("part", "write the parts as an array of tables [[material.part]].")
        base = {k: v for k, v in t.data.items() if k in _MATERIAL_KEYS}
        complete = any(k in base for k in ("lam", "mu", "equilibrium", "nonequilibrium"))  # else defaults only
        if not parts:
            return self.branches(t, "[material]"), density, mass
        n_cells = self.mesh.n_cells
        owner, pairs, names, densities = np.zeros(n_cells, dtype=int), [], [], []
        for i, part in enumerate(parts, 1):
            pt = _Table(self.name, part, f"[[material.part]] {i}", _MATERIAL_KEYS + ("cells", "density"))
            cells = self.cells(pt)
            if owner[cells].any():
                c = cells[owner[cells] > 0][0]
                raise pt.error("cells", f"cell {c} is also in [[material.part]] {owner[c]}; each cell takes one "
                               "material.")
            owner[cells] = i
            # the part's keys replace those of [material]; lam/mu and the branch tables replace each other
            merged = {k: v for k, v in base.items() if not (
                (k in ("lam", "mu") and ("equilibrium" in part or "nonequilibrium" in part))
                or (k in ("equilibrium", "nonequilibrium") and ("lam" in part or "mu" in part)))}
            merged.update({k: v for k, v in part.items() if k not in ("cells", "density")})
            densities.append((pt.number("density", density, positive=True), cells))
            pairs.append((self.branches(_Table(self.name, merged, pt.where, _MATERIAL_KEYS), pt.where), cells))
            names.append(pt.where)
        rest = np.flatnonzero(owner == 0)
        if rest.size and not complete:
            raise t.error("part", f"{rest.size} of {n_cells} cells (the first: cell {rest[0]}) are in no "
                          "[[material.part]]; give [material] lam/mu for them, or parts that cover every cell.")
        if complete:
            pairs.insert(0, (self.branches(t, "[material]"), rest))
            names.insert(0, "[material]")
        viscous = [m.has_internal_variable for m, _ in pairs]
        if len(set(viscous)) > 1:
            i = viscous.index(not viscous[0])
            raise t.error("part", f"{names[i]} is {'viscous' if viscous[i] else 'elastic'} but {names[0]} is not; "
                          "the materials of one body must all be viscous or all elastic.")
        if any(rho != density for rho, _ in densities):
            per_cell = np.full(n_cells, float(density))
            for rho, cells in densities:
                per_cell[cells] = rho
            density = per_cell
        return [(m, c) for m, c in pairs if len(c)], density, mass

    def branches(self, t, where):
        """The `ReeseGovindjee` material of the keys `_MATERIAL_KEYS` of table `t`."""
        from .._materials import NeoHooke, ReeseGovindjee

        eta = {k: t.number(k, math.inf, positive=True, allow_inf=True) for k in ("eta_dev", "eta_vol")}

        def neo_hooke(key):
            tab = _Table(self.name, t.raw(key), f"{where}: {key}", ("lam", "mu")) if key else t
            return NeoHooke(lam=tab.number("lam", positive=True), mu=tab.number("mu", positive=True))

        if t.has("equilibrium"):
            if t.has("lam") or t.has("mu"):
                raise t.error("lam" if t.has("lam") else "mu", "give lam/mu or [material.equilibrium], not both.")
            eq, neq = neo_hooke("equilibrium"), None
            if t.has("nonequilibrium"):
                neq = neo_hooke("nonequilibrium")
            elif any(math.isfinite(v) for v in eta.values()):
                raise t.error("eta_dev" if math.isfinite(eta["eta_dev"]) else "eta_vol",
                              "a finite viscosity needs the viscous branch [material.nonequilibrium].")
        else:
            if t.has("nonequilibrium"):
                raise t.error("nonequilibrium", "give [material.equilibrium] with it (lam/mu make both branches).")
            eq = neo_hooke(None)
            neq = eq if any(math.isfinite(v) for v in eta.values()) else None
        return ReeseGovindjee(eq, neq, **eta)

    def cells(self, t, key="cells"):
        """The cell indices of the groups named by `t[key]`: cell groups of the mesh file,
        or the cells whose nodes all lie in a [groups] node group."""
        out = []
        for gname in t.names(key):
            if gname in self.extra:
                inside = np.zeros(self.mesh.n_nodes, dtype=bool)
                inside[self.extra[gname]] = True
                c = np.flatnonzero(inside[np.asarray(self.mesh.cells)].all(axis=1))
                if not c.size:
                    raise t.error(key, f"[groups.{gname}] contains no whole cell (all nodes of a cell must belong "
                                  "to it).")
                out.append(c)
                continue
            try:
                out.append(np.asarray(self.groups.cell_group(gname)))
            except ValueError as e:
                raise self._missing(t, key, gname, e) from None
        return np.unique(np.concatenate(out))
