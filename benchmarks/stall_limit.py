"""Giving a step up when Newton stalls (`NewtonKrylov.stall_limit`): counts and wall time.

    python benchmarks/stall_limit.py [--t-end 10]

Where a step has no solution near its predictor (eG(2) at h = 1 on the paper scene: the
solution branch folds, `eg2_arclength.py`), Newton with a backtracking line search
creeps: 20 iterations of 4-8 halvings each before the step is halved. `stall_limit`
gives the step up once that many iterations in a row needed `_newton._STALL_HALVINGS`
or more halvings. Per case and rule (off; the default; other limits and halvings), the
run's Newton-Krylov iterations (those of rejected attempts included), Krylov vectors,
rejected attempts, and the wall time of a second call (compiled; one call each, the
rules alternate within a case; each halvings setting is a process of its own). Cases:
the large steps of `large_steps.py` (paper scene, h = 1) and the near-incompressible
variant (lambda = 1000 mu), and the paper scene's adaptive runs to t = 40 (eG(1..3),
rtol = atol = 1e-3). Writes benchmarks/results/stall_limit.json.
"""

import argparse
import json
import subprocess
import sys
import time

from common import PAPER, jv, machine, write_json  # noqa: I001

import numpy as np  # noqa: E402

RULES = [(3, 0), (3, 2), (3, 3), (2, 2), (2, 3), (4, 3)]  # (halvings, stall_limit); (3, 2) the default


def cases(t_end):
    paper, stiff = jv.scenes.lshape(), jv.scenes.lshape(lam=1000 * PAPER["mu"])
    out = [(f"{s.name} h=1", paper, s, dict(t1=t_end, dt0=1.0)) for s in (jv.eG(1), jv.eG(2), jv.eG(3), jv.cG(1),
                                                                         jv.cG(2))]
    out += [(f"{s.name} lambda=1000mu h={h:g}", stiff, s, dict(t1=t_end, dt0=h))
            for s, h in ((jv.eG(1), 1.0), (jv.eG(1), 0.5), (jv.eG(2), 1.0))]
    out += [(f"{s.name} adaptive 1e-3 to t=40", paper, s, dict(t1=40.0, stepsize_controller=jv.PIDController(1e-3, 1e-3)))
            for s in (jv.eG(1), jv.eG(2), jv.eG(3))]
    return out


def worker(halvings, t_end):
    from jaxvisco._solver import _newton

    _newton._STALL_HALVINGS = halvings
    rows = []
    for name, scene, scheme, kw in cases(t_end):
        for h, limit in RULES:
            if h != halvings:
                continue
            solver = jv.NewtonKrylov(stall_limit=limit)
            jv.simulate(scene, scheme, root_finder=solver, throw=False, **kw)
            t0 = time.perf_counter()
            sol = jv.simulate(scene, scheme, root_finder=solver, throw=False, **kw)
            wall = time.perf_counter() - t0
            n = lambda key: int(np.asarray(getattr(sol, key)).sum())  # noqa: E731
            rows.append(dict(case=name, halvings=halvings, stall_limit=limit, status=sol.status,
                             accepted_steps=len(np.asarray(sol.newton_iterations)), newton=n("newton_iterations"),
                             newton_max=int(np.asarray(sol.newton_iterations).max()), krylov=n("krylov_iterations"),
                             chord=n("chord_iterations"), rejections=n("rejections"), wall_s=wall))
            print(json.dumps(rows[-1]), flush=True)
    print("ROWS " + json.dumps(rows))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=10.0)
    ap.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker is not None:
        return worker(a.worker, a.t_end)
    rows = []
    for halvings in sorted({h for h, _ in RULES}):
        out = subprocess.run([sys.executable, __file__, "--worker", str(halvings), "--t-end", str(a.t_end)],
                             capture_output=True, text=True, check=True).stdout
        rows += json.loads(next(line[5:] for line in out.splitlines() if line.startswith("ROWS ")))
        print(f"halvings {halvings}: {len(rows)} rows", flush=True)
    for name in dict.fromkeys(r["case"] for r in rows):
        print(name)
        for r in (r for r in rows if r["case"] == name):
            print(f"  halvings {r['halvings']} limit {r['stall_limit']}: {r['status']}, Newton {r['newton']}, "
                  f"rejections {r['rejections']}, {r['wall_s']:.2f} s")
    write_json("stall_limit.json", dict(machine=machine(), t_end=a.t_end, default=dict(halvings=3, stall_limit=2),
                                        rules=RULES, rows=rows))


if __name__ == "__main__":
    main()
