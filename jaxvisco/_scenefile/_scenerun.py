"""The run settings of a scene file (`_scenefile`): the ``[integrator]``, ``[solver]``,
``[time]`` (a constant step, a schedule, or error-controlled steps) and ``[output]``
tables, read into the integrator, the `NewtonKrylov` solver, the steps and the output
options of a `SceneFile`."""

import os

_INTEGRATORS = {"cg": "cG", "eg": "eG", "newmark": "Newmark", "midpoint": "Midpoint"}
# [solver]: NewtonKrylov's settings (linear_solver "krylov" or "direct") and, for "krylov",
# those of its GMRES (the file keys of jaxvisco 0.1, kept: krylov = "gmres" or "lineax").
_SOLVER_KEYS = dict(rtol=float, max_iterations=int, linear_solver=str, krylov=str, krylov_max_steps=int,
                    refresh_after=int, line_search=int, reuse_limit=int, chord=int, chord_contraction=float,
                    retain=int, preconditioner=str, restart=int, multigrid_precision=str)
_GMRES_KEYS = dict(krylov="backend", krylov_max_steps="max_steps", refresh_after="refresh_after",
                   preconditioner="preconditioner", restart="restart", multigrid_precision="multigrid_precision")


class RunReader:
    """The run-settings method of `_scenefile._Reader` (which provides `name`,
    `base_dir` and `table`)."""

    def run_options(self):
        from .._integrate._schedule import StepTo
        from .._solver._linear import GMRES, krylov_backend
        from .._solver._newton import NewtonKrylov
        from .._time_element._time_element import Midpoint, Newmark, cG, eG

        t = self.table("integrator", ("name", "order"), required=False)
        name = t.string("name", "eG")
        key = name.strip().lower()
        if key not in _INTEGRATORS:
            raise t.error("name", f"got {name!r}; accepted: {', '.join(_INTEGRATORS.values())}.")
        order = t.integer("order", 1, minimum=1)
        if key in ("newmark", "midpoint") and t.has("order"):
            raise t.error("order", f"{_INTEGRATORS[key]} has no order; it applies to cG and eG.")
        integrator = {"cg": lambda: cG(order), "eg": lambda: eG(order), "newmark": Newmark, "midpoint": Midpoint}[key]()

        t = self.table("solver", tuple(_SOLVER_KEYS), required=False)
        kw = {}
        for k, kind in _SOLVER_KEYS.items():
            if t.has(k):
                kw[k] = t.string(k) if kind is str else t.number(k) if kind is float else t.integer(k, minimum=0)
        gmres = {_GMRES_KEYS[k]: kw.pop(k) for k in tuple(kw) if k in _GMRES_KEYS}
        try:
            if "backend" in gmres:
                gmres["backend"] = krylov_backend(gmres["backend"])
            if gmres:
                if kw.get("linear_solver", "krylov") != "krylov":
                    raise ValueError("krylov, krylov_max_steps, refresh_after, preconditioner, restart and "
                                     "multigrid_precision set the Krylov solver, but "
                                     f"linear_solver = {kw['linear_solver']!r}.")
                kw["linear_solver"] = GMRES(**gmres)
            solver = NewtonKrylov(**kw)
        except ValueError as e:
            raise ValueError(f"{self.name}: [solver]: {e}") from None

        t = self.table("time", ("t_end", "dt", "schedule", "max_halvings", "rtol", "atol"))
        rtol = atol = None
        if t.has("rtol") or t.has("atol"):  # error-controlled steps; dt is the first step tried
            if t.has("schedule"):
                raise t.error("schedule", "a schedule fixes the steps; with rtol/atol (error-controlled steps) give "
                              "no schedule (dt, if given, is the first step tried).")
            rtol = t.number("rtol", t.number("atol", None, positive=True) if t.has("atol") else None, positive=True)
            atol = t.number("atol", rtol, positive=True)
            dt = t.number("dt", positive=True) if t.has("dt") else None
            t_end = t.number("t_end", positive=True)
            steps = None
        else:
            if t.has("dt") == t.has("schedule"):
                raise t.error("dt", "give either dt (a constant step) or schedule = [[t_until, dt], ...], not both."
                              if t.has("dt") else "missing: give dt = STEP or schedule = [[t_until, dt], ...] (or "
                              "rtol/atol for error-controlled steps).")
            if t.has("dt"):
                dt = t.number("dt", positive=True)
                t_end = t.number("t_end", positive=True)
            else:
                s = t.raw("schedule")
                ok = isinstance(s, list) and s and all(isinstance(p, list) and len(p) == 2 and all(
                    isinstance(a, (int, float)) and not isinstance(a, bool) for a in p) for p in s)
                if not ok:
                    raise t.error("schedule", f"got {s!r}; accepted: a list of [t_until, dt] pairs, e.g. "
                                  "[[20.0, 0.1], [60.0, 1.0]].")
                dt = tuple((float(a), float(b)) for a, b in s)
                t_end = t.number("t_end", dt[-1][0], positive=True)
            try:
                steps = StepTo.from_schedule(0.0, t_end, dt, t1_name="t_end")
            except ValueError as e:
                raise t.error("schedule" if t.has("schedule") else "dt", str(e)) from None
        max_halvings = t.integer("max_halvings", 6, minimum=0, maximum=30)

        t = self.table("output", ("file", "save_every", "save_gamma", "chunk", "commit_every"), required=False)
        out = os.path.splitext(os.path.basename(self.name))[0] + ".h5"
        output = dict(file=os.path.join(self.base_dir, t.string("file", out)),
                      save_every=t.integer("save_every", 1, minimum=1), save_gamma=t.boolean("save_gamma", False),
                      chunk=t.integer("chunk", 50, minimum=1), commit_every=t.number("commit_every", 5.0, minimum=0))
        return dict(integrator=integrator, solver=solver, steps=steps, t_end=t_end, dt=dt, max_halvings=max_halvings,
                    output=output, rtol=rtol, atol=atol)

