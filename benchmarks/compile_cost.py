"""Where the compile time of a run goes: each part of a step compiled on its own.

    python benchmarks/compile_cost.py [--quick] [--dim 2] [--refinement 1] [--schemes eG(1),eG(2)]

For the L-shape and each scheme, the parts of the compiled time loop are lowered and
compiled as programs of their own: the step residual, its linearization with one JVP,
the condensed tangent (`form_tangent`), the block solve (`schur_solve`), one GMRES solve,
one Newton solve of a step (`solve_step`: all of the above), the step's outcome
(end state, dissipation, external work), the diagnostics of a saved frame, and the whole
`simulate` loop. For each: trace + lowering seconds, XLA compile seconds, and the number
of HLO instructions after XLA's optimization. The parts overlap (a Newton solve contains
the residual, the tangent, ...), so they do not add up to the whole; they show which
piece of the program XLA spends its time on. Every case runs in a fresh process (XLA
caches nothing across processes here). Writes benchmarks/results/compile_cost.json.

    python benchmarks/compile_cost.py --anatomy [--schemes eG(1)] [--top 30]

compiles the whole loop once with XLA's dump on and attributes every instruction of the
optimized program to the jaxvisco functions on its stack (XLA keeps the Python stack of
each instruction): instructions per function (inclusive) and per innermost source line,
and the number of compiled kernels. This is how the loop's size was found to be a third
cyclic-shift cross products (`_tensor.det3`/`inv3` differentiated twice per point).
"""

import argparse
import collections
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import time

from common import jv, lshape, machine, schemes, write_json  # noqa: I001

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from jaxvisco._fem._krylov import gmres  # noqa: E402
from jaxvisco._integrate._differentiable import plan, record_size  # noqa: E402
from jaxvisco._integrate._simulate import _run  # noqa: E402
from jaxvisco._solver._newton import solve_step  # noqa: E402
from jaxvisco._solver._tangent import empty_tangent, form_tangent, schur_solve  # noqa: E402
from jaxvisco._time_element._step import make_context, predictor, residual, step_outcome  # noqa: E402

PARTS = ("residual", "linearize_jvp", "form_tangent", "schur_solve", "gmres", "solve_step", "step_outcome",
         "diagnostics", "simulate")


def _hlo_instructions(compiled):
    return sum(1 for line in compiled.as_text().splitlines() if " = " in line and not line.lstrip().startswith("//"))


def part(name, dim, refinement, scheme_name, mass):
    scene = lshape(dim, refinement, mass=mass)
    scheme = schemes()[scheme_name]
    solver = jv.NewtonKrylov()
    state = scene.initial_state()
    ctx = make_context(scene, state, 0.0, 0.1)
    U = predictor(scheme, scene, ctx, scene.v0)
    tan = empty_tangent(scheme, scene)
    res = lambda c, u: residual(scheme, scene, c, u)  # noqa: E731

    if name == "residual":
        fn, args = res, (ctx, U)
    elif name == "linearize_jvp":
        fn, args = (lambda c, u, v: jax.linearize(lambda w: res(c, w), u)[1](v)), (ctx, U, U)
    elif name == "form_tangent":
        fn, args = (lambda c, u: form_tangent(scheme, scene, c, u)), (ctx, U)
    elif name == "schur_solve":
        fn, args = (lambda c, t, b: schur_solve(scheme, scene, c, t, b, jnp.eye(scene.dim))), (ctx, tan, U)
    elif name == "gmres":
        def fn(c, u, t):
            _, jvp = jax.linearize(lambda w: res(c, w), u)
            precond = lambda r: schur_solve(scheme, scene, c, t, r, jnp.eye(scene.dim))  # noqa: E731
            return gmres(jvp, precond, u, 1e-6, solver.linear_solver.max_steps)[0]
        args = (ctx, U, tan)
    elif name == "solve_step":
        fn, args = (lambda c, u, t: solve_step(solver, scheme, scene, c, u, t)), (ctx, U, tan)
    elif name == "step_outcome":
        def fn(c, u, t):
            r = jv._solver._newton.NewtonResult(u, jnp.asarray(True), jnp.asarray(1), jnp.asarray(1), jnp.asarray(0), jnp.asarray(0.0), t)
            return step_outcome(scheme, scene, c, r)
        args = (ctx, U, tan)
    elif name == "diagnostics":
        fn, args = (lambda s: scene.diagnostics(s)), (state,)
    elif name == "simulate":
        hs = jnp.full(10, 0.1)
    else:
        raise ValueError(f"unknown part {name!r}; known: {PARTS}")

    t0 = time.perf_counter()
    if name == "simulate":
        # The arguments `simulate` passes for a default constant-step run of 10 steps.
        derivative = plan(jv.RecursiveCheckpointAdjoint(), record_size(hs.shape[0]), 1, scheme, scene)
        lowered = _run.lower(scene, scheme, solver, state, jnp.asarray(0.0), hs, jnp.cumsum(hs), jnp.asarray(10), 1,
                             False, None, jv.ConstantStepSize().max_halvings, jnp.zeros_like(state.p),
                             jnp.asarray(False), derivative)
    else:
        lowered = eqx.filter_jit(fn).lower(*args)
    lower_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    compiled = lowered.compile()
    compiled = getattr(compiled, "compiled", compiled)  # equinox wraps jax.stages.Compiled
    compile_s = time.perf_counter() - t0
    return dict(part=name, lower_s=lower_s, compile_s=compile_s, hlo_instructions=_hlo_instructions(compiled))


def _stack_tables(lines):
    """The FileNames / FunctionNames / FileLocations / StackFrames tables of an HLO dump."""
    tables, section = {}, None
    for line in lines:
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            section = tables.setdefault(line, {})
        elif section is not None and not line.strip():
            section = None
        elif section is not None:
            key, rest = line.split(" ", 1)
            section[int(key)] = rest
    files = {k: v.strip('"').split("site-packages/")[-1] for k, v in tables["FileNames"].items()}
    funcs = {k: v.strip('"') for k, v in tables["FunctionNames"].items()}
    locs = {k: tuple(int(x) for x in re.match(r"\{file_name_id=(\d+) function_name_id=(\d+) line=(\d+)", v).groups())
            for k, v in tables["FileLocations"].items()}
    frames = {k: tuple(int(x) for x in re.match(r"\{file_location_id=(\d+) parent_frame_id=(\d+)", v).groups())
              for k, v in tables["StackFrames"].items()}
    return files, funcs, locs, frames


def anatomy(scheme_name, dim, refinement, mass, top):
    """Instructions of the optimized time loop per jaxvisco function and per line."""
    with tempfile.TemporaryDirectory(prefix="jaxvisco-hlo-") as tmp:  # XLA's dump, removed afterwards
        dump = pathlib.Path(tmp)
        env = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} --xla_dump_to={dump}".strip())
        cmd = [sys.executable, __file__, "--worker", f"{scheme_name}|simulate", "--dim", str(dim),
               "--refinement", str(refinement), "--mass", mass]
        subprocess.run(cmd, check=True, capture_output=True, env=env)
        (path,) = dump.glob("*jit__run.cpu_after_optimizations.txt")
        lines = path.read_text().splitlines()
        kernels = sum(1 for p in dump.iterdir() if "jit__run" in p.name and "obj-file" in p.name)
    files, funcs, locs, frames = _stack_tables(lines)
    inclusive, innermost, n = collections.Counter(), collections.Counter(), 0
    for line in lines:
        m = re.search(r"stack_frame_id=(\d+)", line)
        if " = " not in line or m is None:
            continue
        n += 1
        stack, fid = [], int(m.group(1))
        while fid > 0:  # parent ids are one-based; 0 ends the stack
            loc, parent = frames[fid]
            f, fn, ln = locs[loc]
            if "jaxvisco/" in files[f] and "benchmarks" not in files[f]:
                stack.append((files[f].split("jaxvisco/", 1)[1], funcs[fn], ln))
            fid = parent - 1
        for key in {(f, fn) for f, fn, _ in stack}:
            inclusive[key] += 1
        if stack:
            innermost[stack[0]] += 1
    print(f"{scheme_name}: {n} instructions with a stack, {kernels} compiled kernels ({path.name})")
    print("-- instructions per jaxvisco function (inclusive)")
    for (f, fn), c in inclusive.most_common(top):
        print(f"{c:7d}  {f}:{fn}")
    print("-- per innermost jaxvisco source line")
    for (f, fn, ln), c in innermost.most_common(top):
        print(f"{c:7d}  {f}:{ln} ({fn})")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="eG(1) only, the whole loop and the Newton solve")
    p.add_argument("--dim", type=int, default=2)
    p.add_argument("--refinement", type=int, default=1)
    p.add_argument("--mass", default="consistent")
    p.add_argument("--schemes", default=None)
    p.add_argument("--parts", default=None)
    p.add_argument("--out", default="compile_cost")
    p.add_argument("--anatomy", action="store_true", help="attribute the whole loop's instructions")
    p.add_argument("--top", type=int, default=30)
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.anatomy:
        for s in (a.schemes.split(",") if a.schemes else ["eG(1)"]):
            anatomy(s, a.dim, a.refinement, a.mass, a.top)
        return
    if a.worker:
        scheme_name, name = a.worker.split("|")
        print("ROW " + json.dumps(part(name, a.dim, a.refinement, scheme_name, a.mass)), flush=True)
        return
    names = a.schemes.split(",") if a.schemes else (["eG(1)"] if a.quick else ["eG(1)", "eG(2)", "cG(1)"])
    parts = a.parts.split(",") if a.parts else (["solve_step", "simulate"] if a.quick else list(PARTS))
    unknown = [x for x in parts if x not in PARTS] + [x for x in names if x not in schemes()]
    if unknown:
        raise SystemExit(f"unknown part or scheme {unknown}; parts: {PARTS}; schemes: {tuple(schemes())}")
    data = dict(machine=machine(), settings=dict(dim=a.dim, refinement=a.refinement, mass=a.mass,
                                                 solver="NewtonKrylov() defaults", xla_flags="default"), rows=[])
    for s in names:
        for name in parts:
            cmd = [sys.executable, __file__, "--worker", f"{s}|{name}", "--dim", str(a.dim),
                   "--refinement", str(a.refinement), "--mass", a.mass]
            out = subprocess.run(cmd, capture_output=True, text=True)
            rows = [json.loads(line[4:]) for line in out.stdout.splitlines() if line.startswith("ROW ")]
            if not rows:
                raise SystemExit(f"{s} {name} failed:\n{out.stderr[-3000:]}")
            row = dict(scheme=s, **rows[0])
            data["rows"].append(row)
            print(f"{s:6s} {name:14s} lower {row['lower_s']:6.2f}s  compile {row['compile_s']:6.2f}s  "
                  f"HLO {row['hlo_instructions']:6d}", flush=True)
    write_json(f"{a.out}.json", data)


if __name__ == "__main__":
    main()
