"""The run settings of a scene file (`_scenefile`): the ``[integrator]``, ``[solver]``
(with ``[solver.gmres]``), ``[time]``, ``[saveat]`` and ``[output]`` tables, read into
the integrator, the `NewtonKrylov` root finder, the steps and the output options of a
`SceneFile`.

The keys are the Python names: ``[time]`` holds `simulate`'s ``t0``, ``t1``, ``dt0``
(and the step controllers' ``schedule``, ``max_halvings``, ``rtol``, ``atol``),
``[saveat]`` `SaveAt`'s ``every`` and ``gamma``, ``[solver]`` `NewtonKrylov`'s keywords
and ``[solver.gmres]`` `GMRES`'s. The names of jaxvisco 0.1 stay accepted as deprecated
aliases (`_TIME_ALIASES`, `_OUTPUT_ALIASES`, `_SOLVER_ALIASES`); each use adds a note to
`SceneFile.deprecated`.
"""

import os

_INTEGRATORS = {"cg": "cG", "eg": "eG", "newmark": "Newmark", "midpoint": "Midpoint"}
# [solver]: NewtonKrylov's keywords (linear_solver "gmres", "krylov" or "direct"; the
# sub-table [solver.gmres] sets the GMRES).
_SOLVER_KEYS = dict(rtol=float, max_iterations=int, linear_solver=str, line_search=int, stall_limit=int,
                    reuse_limit=int, reuse_band=float, chord=int, chord_contraction=float, retain=int)
_GMRES_KEYS = dict(max_steps=int, refresh_after=int, backend=str, preconditioner=str, restart=int,
                   multigrid_precision=str)
# Deprecated names (jaxvisco 0.1's file keys) -> the key that replaces them.
_SOLVER_ALIASES = dict(krylov="backend", krylov_max_steps="max_steps", refresh_after="refresh_after",
                       preconditioner="preconditioner", restart="restart", multigrid_precision="multigrid_precision")
_TIME_ALIASES = dict(t_end="t1", dt="dt0")
_OUTPUT_ALIASES = dict(save_every="every", save_gamma="gamma")
_LINEAR_SOLVERS = {"gmres": "krylov", "krylov": "krylov", "direct": "direct"}


class RunReader:
    """The run-settings methods of `_scenefile._Reader` (which provides `name`,
    `base_dir`, `doc`, `table` and `notes`)."""

    def run_options(self):
        integrator = self.integrator()
        root_finder = self.root_finder()
        time = self.time()
        saveat, output = self.output()
        return dict(integrator=integrator, root_finder=root_finder, saveat=saveat, output=output, **time)

    def _noted(self, t):
        self.notes.extend(t.deprecated)
        return t

    def integrator(self):
        from .._time_element._time_element import Midpoint, Newmark, cG, eG

        t = self.table("integrator", ("name", "order", "quadrature"), required=False)
        name = t.string("name", "eG")
        key = name.strip().lower()
        if key not in _INTEGRATORS:
            raise t.error("name", f"got {name!r}; accepted: {', '.join(_INTEGRATORS.values())}.")
        order = t.integer("order", 1, minimum=1)
        quadrature = t.integer("quadrature", None, minimum=1)
        if key in ("newmark", "midpoint"):
            for k in ("order", "quadrature"):
                if t.has(k):
                    raise t.error(k, f"{_INTEGRATORS[key]} has no {k}; it applies to cG and eG.")
            return {"newmark": Newmark, "midpoint": Midpoint}[key]()
        try:
            return (cG if key == "cg" else eG)(order, quadrature=quadrature)
        except ValueError as e:
            raise t.error("quadrature", str(e)) from None

    def root_finder(self):
        from .._solver._linear import GMRES, krylov_backend
        from .._solver._newton import NewtonKrylov

        aliases = {k: f"[solver.gmres] {v}" for k, v in _SOLVER_ALIASES.items()}
        t = self._noted(self.table("solver", tuple(_SOLVER_KEYS) + ("gmres",), required=False, aliases=aliases))
        kw = {k: _typed(t, k, kind) for k, kind in _SOLVER_KEYS.items() if t.has(k)}
        if "linear_solver" in kw:
            kw["linear_solver"] = _LINEAR_SOLVERS.get(kw["linear_solver"], kw["linear_solver"])
        old = {_SOLVER_ALIASES[k]: _typed(t, k, str if k == "krylov" else _GMRES_KEYS[_SOLVER_ALIASES[k]])
               for k in _SOLVER_ALIASES if t.has(k)}
        table = None
        if t.has("gmres"):
            from ._scenetable import Table

            table = Table(self.name, t.raw("gmres"), "[solver.gmres]", tuple(_GMRES_KEYS))
        new = {} if table is None else {k: _typed(table, k, kind) for k, kind in _GMRES_KEYS.items() if table.has(k)}
        both = sorted(k for k, v in _SOLVER_ALIASES.items() if t.has(k) and v in new)
        if both:
            raise t.error(both[0], f"give [solver.gmres] {_SOLVER_ALIASES[both[0]]} or the deprecated [solver] "
                          f"{both[0]}, not both.")
        where = "[solver]" if old else "[solver.gmres]"
        try:
            if "backend" in old:
                old["backend"] = krylov_backend(old["backend"])
            gmres = {**old, **new}
            if gmres:
                if kw.get("linear_solver", "krylov") != "krylov":
                    raise ValueError("krylov, krylov_max_steps, refresh_after, preconditioner, restart and "
                                     "multigrid_precision set the Krylov solver, but "
                                     f"linear_solver = {t.raw('linear_solver')!r}." if old else
                                     f"[solver.gmres] sets the Krylov solver, but "
                                     f"linear_solver = {t.raw('linear_solver')!r}.")
                try:
                    kw["linear_solver"] = GMRES(**gmres)
                except ValueError as e:
                    raise ValueError(f"{where}: {e}" if where != "[solver]" else str(e)) from None
            return NewtonKrylov(**kw)
        except ValueError as e:
            msg = str(e)
            prefix = "" if msg.startswith("[solver.gmres]") else "[solver]: "
            raise ValueError(f"{self.name}: {prefix}{msg}") from None

    def time(self):
        from .._integrate._schedule import StepTo

        aliases = {k: v for k, v in _TIME_ALIASES.items()}
        t = self._noted(self.table("time", ("t0", "t1", "dt0", "schedule", "max_halvings", "rtol", "atol"),
                                   aliases=aliases))
        t1_key, dt_key = _either(t, "t1", "t_end"), _either(t, "dt0", "dt")
        t0 = t.number("t0", 0.0)
        rtol = atol = None
        if t.has("rtol") or t.has("atol"):  # error-controlled steps; dt0 is the first step tried
            if t.has("schedule"):
                raise t.error("schedule", f"a schedule fixes the steps; with rtol/atol (error-controlled steps) give "
                              f"no schedule ({dt_key}, if given, is the first step tried).")
            rtol = t.number("rtol", t.number("atol", None, positive=True) if t.has("atol") else None, positive=True)
            atol = t.number("atol", rtol, positive=True)
            dt0 = t.number(dt_key, positive=True) if t.has(dt_key) else None
            t1 = _later(t, t1_key, t0)
            steps = None
        else:
            if t.has(dt_key) == t.has("schedule"):
                raise t.error(dt_key, f"give either {dt_key} (a constant step) or schedule = [[t_until, dt], ...], "
                              "not both." if t.has(dt_key) else f"missing: give {dt_key} = STEP or schedule = "
                              "[[t_until, dt], ...] (or rtol/atol for error-controlled steps).")
            if t.has(dt_key):
                dt0 = t.number(dt_key, positive=True)
                t1 = _later(t, t1_key, t0)
            else:
                s = t.raw("schedule")
                ok = isinstance(s, list) and s and all(isinstance(p, list) and len(p) == 2 and all(
                    isinstance(a, (int, float)) and not isinstance(a, bool) for a in p) for p in s)
                if not ok:
                    raise t.error("schedule", f"got {s!r}; accepted: a list of [t_until, dt] pairs, e.g. "
                                  "[[20.0, 0.1], [60.0, 1.0]].")
                dt0 = tuple((float(a), float(b)) for a, b in s)
                t1 = _later(t, t1_key, t0, dt0[-1][0])
            try:
                steps = StepTo.from_schedule(t0, t1, dt0, t1_name=t1_key)
            except ValueError as e:
                raise t.error("schedule" if t.has("schedule") else dt_key, str(e)) from None
        max_halvings = t.integer("max_halvings", 6, minimum=0, maximum=30)
        return dict(steps=steps, t0=t0, t1=t1, dt0=dt0, max_halvings=max_halvings, rtol=rtol, atol=atol)

    def output(self):
        from .._integrate._saveat import SaveAt

        aliases = {k: f"[saveat] {v}" for k, v in _OUTPUT_ALIASES.items()}
        t = self._noted(self.table("output", ("file", "chunk", "commit_every"), required=False, aliases=aliases))
        s = self.table("saveat", ("every", "gamma"), required=False)
        for old, new in _OUTPUT_ALIASES.items():
            if t.has(old) and s.has(new):
                raise t.error(old, f"give [saveat] {new} or the deprecated [output] {old}, not both.")
        every = s.integer("every", None, minimum=1) if s.has("every") else t.integer("save_every", 1, minimum=1)
        gamma = s.boolean("gamma", False) if s.has("gamma") else t.boolean("save_gamma", False)
        out = os.path.splitext(os.path.basename(self.name))[0] + ".h5"
        output = dict(file=os.path.join(self.base_dir, t.string("file", out)),
                      chunk=t.integer("chunk", 50, minimum=1), commit_every=t.number("commit_every", 5.0, minimum=0))
        return SaveAt(every=every, gamma=gamma), output


def _typed(t, key, kind):
    return t.string(key) if kind is str else t.number(key) if kind is float else t.integer(key, minimum=0)


def _either(t, new, old):
    """The name under which `t` gives a key: `new`, or its deprecated alias `old`
    (`new` where neither is given); both at once is an error."""
    if t.has(new) and t.has(old):
        raise t.error(old, f"give {new} or the deprecated {old}, not both.")
    return old if t.has(old) else new


def _later(t, key, t0, default=None):
    """The end time `t[key]` (or `default`), checked to lie after `t0`."""
    if default is not None and not t.has(key):
        return default
    t1 = t.number(key)
    if not t1 > t0:
        raise t.error(key, f"got {t1!r}; accepted: a time after t0 = {t0!r}.")
    return t1
