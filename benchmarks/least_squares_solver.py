"""jaxvisco.least_squares against optimistix.LevenbergMarquardt: evaluations, memory, time.

    python benchmarks/least_squares_solver.py [--quick]

1. Evaluations per fit (each one residual + Jacobian) from starts off by a factor 3 in
   every direction, exact data and noisy data, on two small models:
   `a exp(-t/tau) + c` (a positive, tau in [0.1, 10], c free) and
   `a1 exp(-t/tau1) + a2 exp(-t/tau2)` (a positive, tau1 in [0.01, 1], tau2 in [1, 100]).
   optimistix works in the same unconstrained variables (`_bounds.Bounds`); its steps each
   evaluate the residual and its linearization once.
2. The Jacobian of a time loop, as each solver forms it: `jax.jacfwd` (jaxvisco) against
   `jax.linearize` and the Jacobian materialized from the linear map (optimistix with
   `jac="fwd"` and a QR solver): XLA's temporary buffers of the compiled programs
   (deterministic), and the run time, for a `scan` (fixed steps) and a `while_loop`
   (adaptive steps) of an explicit ODE with 200 states and p = 3 parameters.
3. `--compile` (several minutes): XLA's compile time of one least-squares iteration with a
   `simulate` residual (2D L-shape, eG(1), 20 steps, probe displacements; eta_dev and
   eta_vol) alone, as `least_squares` compiles it at top level, against the same
   iteration nested in a `lax.while_loop` (as under `jax.vmap`); fresh processes,
   alternating.
"""

import argparse
import itertools
import json
import subprocess
import sys
import time

from common import machine, write_json  # noqa: I001

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import jaxvisco as jv
from jaxvisco._tools._bounds import make_bounds


def _one_exponential():
    t = jnp.linspace(0.0, 5.0, 100)
    true = np.array([2.0, 1.3, 0.5])
    model = lambda x, t: x[0] * jnp.exp(-t / x[1]) + x[2]  # noqa: E731
    return t, true, model, [0.0, 0.1, -np.inf], [np.inf, 10.0, np.inf], 0.05


def _two_exponentials():
    t = jnp.logspace(-2, 2, 80)
    true = np.array([1.0, 0.1, 0.5, 10.0])
    model = lambda x, t: x[0] * jnp.exp(-t / x[1]) + x[2] * jnp.exp(-t / x[3])  # noqa: E731
    return t, true, model, [0.0, 0.01, 0.0, 1.0], [np.inf, 1.0, np.inf, 100.0], 0.01


def evaluations(problem, noisy):
    t, true, model, lower, upper, noise = problem()
    y = model(true, t)
    if noisy:
        y = y + noise * np.random.default_rng(0).standard_normal(t.shape)

    def residual(x, data):
        return model(x, data[0]) - data[1]

    starts = [true * np.array(f) for f in itertools.product([3.0, 1 / 3], repeat=len(true))]
    ours, theirs = [], []
    for start in starts:
        t0 = time.perf_counter()
        fit = jv.least_squares(residual, start, (t, y), lower=lower, upper=upper)
        wall = time.perf_counter() - t0
        ours.append(dict(evaluations=int(fit.iterations), converged=fit.converged, wall_s=wall,
                         error=float(np.max(np.abs(np.asarray(fit.values) / true - 1)))))
        bounds = make_bounds(start, lower, upper, [f"x{i}" for i in range(len(true))])
        solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
        fz = lambda z, data: residual(bounds.to_physical(z), data)  # noqa: E731
        t0 = time.perf_counter()
        sol = optx.least_squares(fz, solver, bounds.to_unconstrained(start), args=(t, y), max_steps=200,
                                 throw=False)
        value = np.asarray(bounds.to_physical(sol.value))
        wall = time.perf_counter() - t0
        theirs.append(dict(evaluations=int(sol.stats["num_steps"]), wall_s=wall,
                           converged=bool(sol.result == optx.RESULTS.successful),
                           error=float(np.max(np.abs(value / true - 1)))))
    return dict(ours=ours, optimistix=theirs)


def _ode(loop, n=200, steps=2000, h=1e-3):
    """An explicit Euler loop y' = -k1 A y + k2 sin(y) + k3, observed at every step."""
    A = jnp.asarray(np.diag(np.linspace(1.0, 3.0, n)))

    def rhs(k, y):
        return -k[0] * A @ y + k[1] * jnp.sin(y) + k[2]

    def residual(k):
        if loop == "scan":
            def step(y, _):
                y = y + h * rhs(k, y)
                return y, y[0]

            return jax.lax.scan(step, jnp.ones(n), None, length=steps)[1]

        def body(c):
            i, y, out = c
            y = y + h * rhs(k, y)
            return i + 1, y, out.at[i].set(y[0])

        return jax.lax.while_loop(lambda c: c[0] < steps, body, (0, jnp.ones(n), jnp.zeros(steps)))[2]

    return residual


def jacobian_cost(loop, repeats):
    residual = _ode(loop)
    k = jnp.asarray([1.0, 0.3, 0.1])

    def forward(k):
        return jax.jacfwd(residual)(k)

    def linearized(k):
        _, lin = jax.linearize(residual, k)
        return jax.vmap(lin, out_axes=1)(jnp.eye(3))  # what lineax's QR materializes

    out = {}
    for name, fn in (("jacfwd", forward), ("linearize", linearized)):
        compiled = jax.jit(fn).lower(k).compile()
        memory = compiled.memory_analysis()
        compiled(k).block_until_ready()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            compiled(k).block_until_ready()
            times.append(time.perf_counter() - t0)
        out[name] = dict(temp_bytes=int(memory.temp_size_in_bytes), wall_s_median=float(np.median(times)))
    primal = jax.jit(residual).lower(k).compile()
    primal(k).block_until_ready()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        primal(k).block_until_ready()
        times.append(time.perf_counter() - t0)
    out["primal_wall_s_median"] = float(np.median(times))
    np.testing.assert_allclose(forward(k), linearized(k), rtol=1e-10, atol=1e-12)
    return out


def _compile_one(mode):
    """Lower and compile one iteration, alone or in a while_loop; print the seconds."""
    from jaxvisco._tools import _least_squares as L
    from jaxvisco._tools._identify import _Run, with_parameters

    scene = jv.scenes.lshape(dim=2)
    probe = jv.Probe(scene.mesh, [[1.0, 1.0], [2.5, 8.0], [5.5, 2.5]])
    run = _Run.of(None, 2.0, 0.1, None, jv.SaveAt(every=2))

    def residual(x, data):
        sc = with_parameters(scene, {"eta_dev": x[0], "eta_vol": x[1]})
        return probe.displacements(run.simulate(sc, jv.eG(1), jv.NewtonKrylov(rtol=1e-11)).x).ravel() - data

    start = np.array([1.5e5, 1e4 / 3])
    bounds = make_bounds(start, [0.0, 0.0], None, ["eta_dev", "eta_vol"])
    problem = L._Problem(residual, None, 50, jnp.zeros(66), jnp.ones(66), bounds,
                         jnp.asarray([1e-10, 1e-14, 1e-10, 1e-8, 1.0, 2.0, 1 / 64]))
    z0 = bounds.to_unconstrained(start)
    f64, i32 = (lambda v: jnp.asarray(v, jnp.float64)), (lambda v: jnp.asarray(v, jnp.int32))  # noqa: E731
    s0 = L._State(z0, jnp.zeros(66), jnp.zeros((66, 2)), f64(jnp.inf), z0, f64(0.0), f64(1e-2), f64(1.0), i32(0),
                  i32(0), i32(0), f64(jnp.full(51, jnp.nan)), f64(jnp.full((51, 2), jnp.nan)))
    if mode == "alone":
        fn = L._iteration
    else:
        def fn(problem, s):
            return jax.lax.while_loop(lambda s: s.status == 0, lambda s: L._iteration(problem, s), s)
    t0 = time.perf_counter()
    lowered = eqx.filter_jit(fn, compiler_options=jv.compiler_options()).lower(problem, s0)
    t1 = time.perf_counter()
    lowered.compile()
    print(json.dumps(dict(mode=mode, trace_s=t1 - t0, compile_s=time.perf_counter() - t1)), flush=True)


def compile_cost(pairs):
    out = []
    for _ in range(pairs):
        for mode in ("alone", "while_loop"):
            proc = subprocess.run([sys.executable, __file__, "--compile-one", mode], capture_output=True, text=True,
                                  check=True)
            out.append(json.loads(proc.stdout.strip().splitlines()[-1]))
            print(out[-1], flush=True)
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--compile", action="store_true", help="also time compilation with a simulate residual")
    p.add_argument("--compile-one", choices=["alone", "while_loop"], help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.compile_one:
        return _compile_one(args.compile_one)
    repeats = 3 if args.quick else 9
    info = machine()
    results = dict(machine=info, evaluations={}, jacobian={})
    for name, problem in (("one_exponential", _one_exponential), ("two_exponentials", _two_exponentials)):
        for noisy in (False, True):
            key = f"{name}_{'noisy' if noisy else 'exact'}"
            r = evaluations(problem, noisy)
            results["evaluations"][key] = r
            for solver, runs in r.items():
                ev = [x["evaluations"] for x in runs]
                print(f"{key:28s} {solver:10s} evaluations {ev} total {sum(ev)} max {max(ev)} "
                      f"converged {sum(x['converged'] for x in runs)}/{len(runs)} "
                      f"max error {max(x['error'] for x in runs):.1e}")
    for loop in ("scan", "while_loop"):
        r = jacobian_cost(loop, repeats)
        results["jacobian"][loop] = r
        print(f"{loop:10s} primal {r['primal_wall_s_median'] * 1e3:.1f} ms; " + "; ".join(
            f"{k}: temp {v['temp_bytes'] / 1e6:.2f} MB, {v['wall_s_median'] * 1e3:.1f} ms"
            for k, v in r.items() if isinstance(v, dict)))
    if args.compile:
        results["compile"] = compile_cost(1 if args.quick else 2)
    write_json("least_squares_solver.json", results)


if __name__ == "__main__":
    main()
