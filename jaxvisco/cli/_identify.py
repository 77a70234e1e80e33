"""``jaxvisco identify FIT.toml``: fit material parameters to experiments described by
scene files and CSV data.

A fit file (paths relative to it)::

    [parameters]                      # what is fitted: a start value (positive), or bounds too
    eta_dev = 6.0
    mu_neq = { start = 6.0, lower = 0.1, upper = 100.0 }

    [fit]                             # optional
    method = "lm"                     # or "lbfgs"
    max_iterations = 30
    confidence = 0.95

    [output]                          # optional
    report = "fit.json"
    plot = "fit.png"

    [[experiment]]
    name = "relaxation"               # default: the data file's name
    scene = "relaxation.toml"         # a scene file: mesh, material, supports, loads, steps
    data = "relaxation.csv"           # a header row, then rows: time, then one column each
    sigma = { force = 0.5 }           # optional noise level per column

    [[experiment.observe]]            # one per data column used
    column = "force"
    reaction = "grip"                 # the supports' force on this node group ...
    component = "x"

    [[experiment.observe]]
    column = "marker"
    point = [20.0, 10.0, 5.0]         # ... or the displacement of a material point ...
    component = "y"

    [[experiment.observe]]
    column = "elongation"
    extensometer = [[10.0, 5.0, 5.0], [30.0, 5.0, 5.0]]   # ... or the change of a gauge length

Each scene file is the test's whole run, in the names of `jaxvisco run` and Python: its
material gives the parameters that are not fitted, its [time] table the times and steps
(t0, t1, dt0, or rtol/atol), its [solver] table the Newton solver (without one, that of
`jv.Experiment`). Anything wrong in either file stops with one line that names it. The
user guide's page "Identification from experiments" describes the format.
"""

import json
import os
import sys

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

import numpy as np

_TOP = ("parameters", "fit", "output", "experiment")
_EXPERIMENT = ("name", "scene", "data", "sigma", "observe")
_OBSERVE = ("column", "reaction", "point", "extensometer", "component")
_KINDS = ("reaction", "point", "extensometer")


def _keys(where, table, accepted):
    if not isinstance(table, dict):
        raise ValueError(f"{where}: expected a table, got {table!r}.")
    unknown = sorted(set(table) - set(accepted))
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r}; accepted: {', '.join(accepted)}.")


def _number(where, value):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ValueError(f"{where}: expected a finite number, got {value!r}.")
    return float(value)


def read_fit_file(path):
    """The experiments and parameters of a fit file (see the module docstring), checked.
    **Returns:** (experiments, parameters, fit options, output paths)."""
    import jaxvisco as jv
    from .._integrate._schedule import ConstantStepSize, Schedule
    from .._integrate._stepsize import PIDController
    from .._scenefile._scenefile import read_scene_file

    name = os.fspath(path)
    if not os.path.isfile(name):
        raise FileNotFoundError(f"fit file {name!r} does not exist.")
    base = os.path.dirname(os.path.abspath(name))
    try:
        with open(name, "rb") as f:
            doc = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{name}: not valid TOML: {e}") from None
    _keys(name, doc, _TOP)
    params = {}
    ptable = doc.get("parameters")
    if not ptable:
        raise ValueError(f"{name}: [parameters]: missing; name at least one parameter to fit, e.g. eta_dev = 1.0.")
    for pname, spec in ptable.items():
        where = f"{name}: [parameters] {pname}"
        if pname not in jv.PARAMETERS:
            raise ValueError(f"{where}: unknown parameter; accepted: {', '.join(sorted(jv.PARAMETERS))}.")
        if isinstance(spec, dict):
            _keys(where, spec, ("start", "lower", "upper"))
            if "start" not in spec:
                raise ValueError(f"{where}: missing start.")
            start = _number(f"{where}: start", spec["start"])
            lower = _number(f"{where}: lower", spec.get("lower", 0.0))
            upper = float("inf") if "upper" not in spec else _number(f"{where}: upper", spec["upper"])
            if not lower < start < upper:
                raise ValueError(f"{where}: start = {start:g} must lie strictly inside its bounds ({lower:g}, "
                                 f"{upper:g}).")
            params[pname] = jv.Parameter(start, lower, upper)
        else:
            start = _number(where, spec)
            if not start > 0:
                raise ValueError(f"{where}: a start value alone makes the parameter positive; got {start:g}.")
            params[pname] = start
    fit = doc.get("fit", {})
    _keys(f"{name}: [fit]", fit, ("method", "max_iterations", "confidence"))
    options = dict(method=fit.get("method", "lm"), max_iterations=int(fit.get("max_iterations", 50)),
                   confidence=float(fit.get("confidence", 0.95)))
    if options["method"] not in ("lm", "lbfgs"):
        raise ValueError(f"{name}: [fit] method: got {options['method']!r}; accepted: 'lm', 'lbfgs'.")
    out = doc.get("output", {})
    _keys(f"{name}: [output]", out, ("report", "plot"))
    stem = os.path.splitext(name)[0]
    outputs = {k: os.path.join(base, out.get(k, os.path.basename(stem) + suffix))
               for k, suffix in (("report", ".json"), ("plot", ".png"))}
    exps = []
    entries = doc.get("experiment")
    if not entries or not isinstance(entries, list):
        raise ValueError(f"{name}: [[experiment]]: missing; describe at least one test.")
    for i, e in enumerate(entries, 1):
        where = f"{name}: [[experiment]] {i}"
        _keys(where, e, _EXPERIMENT)
        for key in ("scene", "data", "observe"):
            if key not in e:
                raise ValueError(f"{where}: missing {key}.")
        sf = read_scene_file(os.path.join(base, e["scene"]))
        data_path = os.path.join(base, e["data"])
        if not os.path.isfile(data_path):
            raise FileNotFoundError(f"{where}: data file {data_path!r} does not exist.")
        columns, values = jv.read_csv(data_path)
        observe, used = [], []
        for j, o in enumerate(e["observe"], 1):
            ow = f"{where}: [[experiment.observe]] {j}"
            _keys(ow, o, _OBSERVE)
            col = o.get("column")
            if col not in columns[1:]:
                raise ValueError(f"{ow}: column {col!r} is not in {e['data']}; its columns: {columns[1:]}.")
            kinds = [k for k in _KINDS if k in o]
            if len(kinds) != 1:
                raise ValueError(f"{ow}: give one of reaction = \"GROUP\", point = [x, y, z] or extensometer = "
                                 "[[...], [...]].")
            try:
                if kinds[0] == "reaction":
                    observe.append(jv.ReactionForce(sf.nodes(o["reaction"]), o.get("component", "x"), name=col))
                elif kinds[0] == "point":
                    observe.append(jv.Displacement(sf.scene.mesh, [o["point"]], o.get("component", "x"), name=col))
                else:
                    a, b = o["extensometer"]
                    observe.append(jv.Extensometer(sf.scene.mesh, a, b, name=col))
            except (ValueError, TypeError) as err:
                raise ValueError(f"{ow}: {' '.join(str(err).split())}") from None
            used.append(columns.index(col))
        sigma = e.get("sigma")
        if sigma is not None:
            _keys(f"{where}: sigma", sigma, [columns[k] for k in used])
            missing = [columns[k] for k in used if columns[k] not in sigma]
            if missing:
                raise ValueError(f"{where}: sigma: give a noise level for every observed column or none; "
                                 f"missing {missing[0]!r}.")
            sigma = [_number(f"{where}: sigma {columns[k]}", sigma[columns[k]]) for k in used]
        run = dict(t0=float(sf.t0), t1=float(sf.t1), name=e.get("name", os.path.splitext(e["data"])[0]))
        if "solver" in tomllib.loads(sf.source):  # else Experiment's own default (as in Python)
            run.update(root_finder=sf.root_finder)
        if sf.rtol is not None:
            run.update(stepsize_controller=PIDController(sf.rtol, sf.atol), dt0=sf.dt0)
        elif isinstance(sf.dt0, (int, float)):
            run.update(stepsize_controller=ConstantStepSize(max_halvings=sf.max_halvings), dt0=float(sf.dt0))
        else:
            run.update(stepsize_controller=Schedule(list(sf.dt0), max_halvings=sf.max_halvings))
        try:
            exps.append(jv.Experiment(sf.scene, sf.integrator, values[:, 0], values[:, used], observe, sigma, **run))
        except (ValueError, TypeError) as err:
            raise ValueError(f"{where}: {' '.join(str(err).split())}") from None
    return exps, params, options, outputs


def _identify(args):
    """`jaxvisco identify`: fit, print value +- interval per parameter, write the report
    and the plot."""
    import jaxvisco as jv

    exps, params, options, outputs = read_fit_file(args.fit)
    if args.report:
        outputs["report"] = args.report
    if args.plot:
        outputs["plot"] = args.plot
    if not args.quiet:
        print(f"jaxvisco identify: {len(exps)} experiment(s), fitting {', '.join(params)}", flush=True)
    fit = jv.identify(exps, params, verbose=not args.quiet, **options)
    level = round(100 * fit.confidence)
    for n in fit.names:
        lo, hi = fit.intervals[n]
        flag = "" if fit.identifiable[n] else "  (not identifiable from these data)"
        print(f"{n} = {fit.params[n]:.6g}  {level} % interval [{lo:.6g}, {hi:.6g}]{flag}")
    print(fit.message)
    with open(outputs["report"], "w") as f:
        json.dump(fit.report(), f, indent=1)
    fit.plot(outputs["plot"])
    if not args.quiet:
        print(f"wrote {outputs['report']} and {outputs['plot']}", file=sys.stderr)
    return 0 if fit.converged else 1
