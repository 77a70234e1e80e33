"""Cost of one time step: Newton and Krylov iterations, ms per step, compile time.

    python benchmarks/step_cost.py [--quick] [--cases "2D r4 lumped,1,default"] [--out NAME]

Runs eG(1) and eG(2) on the 2D L-shape at refinement 1 and 4 (consistent mass, and
lumped at refinement 4: issue #16's case) and the 3D L-shape at refinement 1 with
h = 0.1: the default solver (chord iterations, then Newton–Krylov), Newton–Krylov alone
(`chord=0`, the default before) and, for eG(1), the direct solver. Writes
benchmarks/results/step_cost.json. `rhs_per_step` is the step's wall time in
right-hand-side evaluations of the same semi-discrete ODE (`jv.semidiscrete`, lumped
mass: the unit of issue #16's target). Timings are wall clock after compilation (median of
repeats); compile time is the first call minus a timed call. Every case runs in its own
subprocess: in one long-lived process the later cases ran up to 1.6x slower (3D r1 eG(1):
50 ms/step after ten other cases against 31-34 ms alone).
"""

import argparse
import json
import statistics
import subprocess
import sys
import time

from common import jv, lshape, machine, write_json  # noqa: I001

import jax  # noqa: E402
from jaxvisco._time_element._step import make_context, residual, predictor  # noqa: E402
from jaxvisco._config import jit  # noqa: E402
import numpy as np  # noqa: E402


def residual_ms(scene, scheme, h):
    """Median and minimum over repeats of one jitted residual evaluation [ms]."""
    ctx = make_context(scene, scene.initial_state(), 0.0, h)
    U = predictor(scheme, scene, ctx, scene.v0)
    f = jit(lambda s, c, u: residual(scheme, s, c, u))  # with the loop's XLA options
    jax.block_until_ready(f(scene, ctx, U))
    t = []
    for _ in range(20):
        t0 = time.perf_counter()
        jax.block_until_ready(f(scene, ctx, U))
        t.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(t), 1e3 * min(t)


def rhs_ms(scene, n=50):
    """One right-hand side of the scene's ODE [ms] (pass a lumped-mass scene: a consistent
    mass adds CG iterations that are not the physics): `n` evaluations chained in one
    compiled loop with the time loop's XLA options (each input depends on the last
    output, so none is skipped), the minimum over repeats divided by `n`. Timed as one
    host call each (before session 31), dispatch was part of every evaluation (0.41-0.58 ms
    on 2D r4 across runs; chained 0.40-0.44 ms)."""
    ode = jv.semidiscrete(scene)
    y = jax.numpy.asarray(ode.y0)

    @jit(plain=True)  # with the time loop's XLA options
    def chain(y):
        return jax.lax.fori_loop(0, n, lambda i, z: z + 1e-30 * ode.vector_field(0.0, z), y)

    jax.block_until_ready(chain(y))
    t = []
    for _ in range(10):
        t0 = time.perf_counter()
        jax.block_until_ready(chain(y))
        t.append(time.perf_counter() - t0)
    return 1e3 * min(t) / n


def case(scene, scheme, solver, n_steps, rhs_scene, h=0.1, repeats=5):
    t0 = time.perf_counter()
    sol = jv.simulate(scene, scheme, t1=n_steps * h, dt0=h, root_finder=solver, saveat=jv.SaveAt(every=n_steps))
    first = time.perf_counter() - t0
    res_med, res_min = residual_ms(scene, scheme, h)
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sol = jv.simulate(scene, scheme, t1=n_steps * h, dt0=h, root_finder=solver, saveat=jv.SaveAt(every=n_steps))
        walls.append(time.perf_counter() - t0)
    wall = statistics.median(walls)
    best = min(walls)
    its = np.asarray(sol.newton_iterations)
    kits = np.asarray(sol.krylov_iterations)
    return dict(
        integrator=scheme.name, linear_solver="direct" if isinstance(solver.linear_solver, jv.Direct) else "krylov", steps=n_steps, h=h,
        dofs=int(scene.mesh.n_nodes * scene.dim), status=sol.status,
        newton_per_step=float(its.mean()), krylov_per_newton=float(kits.sum() / max(its.sum(), 1)),
        chord_per_step=float(np.mean(np.asarray(sol.chord_iterations))),
        ms_per_step=1e3 * wall / n_steps, ms_per_step_min=1e3 * best / n_steps, compile_s=first - wall,
        residual_eval_ms=res_med, residual_eval_ms_min=res_min,
        residuals_per_step=best / n_steps / (1e-3 * res_min),
        rhs_eval_ms_min=(r := rhs_ms(rhs_scene)), rhs_per_step=best / n_steps / (1e-3 * r),
    )


SCENES = {"2D r1": (2, 1, "consistent"), "2D r4": (2, 4, "consistent"), "2D r4 lumped": (2, 4, "lumped"),
          "3D r1": (3, 1, "consistent")}
SOLVERS = {"default": {}, "chord=0": dict(chord=0), "direct": dict(linear_solver=jv.Direct())}
CASES = [(1, "default"), (1, "chord=0"), (1, "direct"), (2, "default"), (2, "chord=0")]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--case", default=None, help=argparse.SUPPRESS)  # scene,k,solver,steps (worker)
    p.add_argument("--cases", default=None,
                   help="only these cases, 'scene,k,solver' joined by ';' (e.g. '2D r4 lumped,1,default')")
    p.add_argument("--steps", type=int, default=None, help="steps per timed run (default 40, --quick 10)")
    p.add_argument("--out", default="step_cost")
    a = p.parse_args(argv)
    if a.case:
        name, k, sv, n = a.case.split(",")
        dim, ref, mass = SCENES[name]
        r = case(lshape(dim, ref, mass=mass), jv.eG(int(k)), jv.NewtonKrylov(**SOLVERS[sv]), int(n),
                 lshape(dim, ref, mass="lumped"))
        r.update(scene=name, solver=sv)
        print("RESULT " + json.dumps(r), flush=True)
        return
    n = a.steps or (10 if a.quick else 40)
    mach = machine()
    rows = []
    only = None if a.cases is None else [tuple(c.split(",")) for c in a.cases.split(";")]
    for name in SCENES:
        for k, sv in CASES:
            if a.quick and (k > 1 or sv == "direct"):
                continue
            if only is not None and (name, str(k), sv) not in only:
                continue
            out = subprocess.run([sys.executable, __file__, "--case", f"{name},{k},{sv},{n}"],
                                 capture_output=True, text=True, check=True).stdout
            r = json.loads(next(line[7:] for line in out.splitlines() if line.startswith("RESULT ")))
            rows.append(r)
            print(json.dumps(r), flush=True)
    write_json(f"{a.out}.json", dict(machine=mach, settings=dict(
        quick=a.quick, cases=a.cases, steps=n,
        scheme_solver="eG(1), eG(2); NewtonKrylov() (chord iterations, then Newton-Krylov), "
                      "NewtonKrylov(chord=0), NewtonKrylov(linear_solver=Direct())",
        timing="ms_per_step: median of 5 timed runs of n steps; _min: their minimum; residuals_per_step = "
               "ms_per_step_min / residual_eval_ms_min (one jitted residual evaluation, min of 20)"), rows=rows))


if __name__ == "__main__":
    main()
