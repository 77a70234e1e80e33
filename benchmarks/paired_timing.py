"""Load-matched timings around error 1e-6: jaxvisco and scipy runs interleaved.

    python benchmarks/paired_timing.py [--rounds 3]

On a shared machine the load changes between the blocks of work_precision.py (the same
computation, cG(1) and Midpoint, was timed 6x apart there). This script re-times the runs
that bracket error 1e-6 on the 2D L-shape r1 (lumped mass, t in [0, 10]) in alternation,
round after round, so every method sees the same load; the errors are those of
work_precision.json (the computations are deterministic). Writes
benchmarks/results/paired_timing.json.
"""

import argparse
import json
import statistics
import time

from common import RESULTS, jv, lshape, machine, write_json  # noqa: I001

import jax  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import work_precision as wp  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--quick", action="store_true", help="one round")
    a = p.parse_args(argv)
    rounds = 1 if a.quick else a.rounds
    T = 10.0
    scene = lshape(2, 1, mass="lumped")
    ode = jv.semidiscrete(scene)
    cap = 800  # as in work_precision.py for eG(2) (h down to 0.0125)
    cases = {}
    for h in (0.05, 0.025, 0.0125):
        cases[("eG(2)", h)] = lambda h=h: jv.simulate(scene, jv.eG(2), t1=T, dt0=h, saveat=jv.SaveAt(every=cap),
                                                      max_steps=cap)
    for m in ("Radau", "BDF"):
        for tol in (1e-5, 1e-6, 1e-7, 1e-8):
            cases[(f"scipy {m}", tol)] = lambda m=m, tol=tol: solve_ivp(ode.fun, (0.0, T), ode.y0, method=m,
                                                                          jac=ode.jac, rtol=tol, atol=tol)
    t0 = time.perf_counter()
    cases[("eG(2)", 0.05)]()
    jax.block_until_ready(ode.rhs(0.0, ode.y0))
    ode.jac(0.0, ode.y0)
    warm = time.perf_counter() - t0
    times = {k: [] for k in cases}
    for _ in range(rounds):
        for k, fn in cases.items():
            t0 = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t0)
            print(k, f"{times[k][-1]:.2f}s", flush=True)
    while not (RESULTS / "work_precision.json").exists():  # written by a run that may still be going
        time.sleep(10)
    src = json.loads((RESULTS / "work_precision.json").read_text())["scenes"]["2D L-shape r1"]["runs"]
    runs = []
    for (m, par), ts in times.items():
        key = "h" if m.startswith("eG") else "rtol"
        err = next((r["error"] for r in src if r["method"] == m and r.get(key) == par), None)
        runs.append(dict(method=m, **{key: par}, error=err, wall_s=statistics.median(ts), times_s=ts))
    at, best, speedup = wp.compare(runs)
    data = {"machine": machine(), "settings": dict(rounds=rounds, t_end=T, warmup_s=warm,
                                                   errors="from work_precision.json (deterministic computations)"),
            "runs": runs, "wall_at_1e-6_s": at, "best_jaxvisco": best, "speedup_at_1e-6": speedup}
    print(at, speedup, flush=True)
    write_json("paired_timing.json", data)


if __name__ == "__main__":
    main()
