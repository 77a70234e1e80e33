"""What a user waits for before the first step: compile on a cold start and from the cache.

    python benchmarks/startup.py [--repeats 3] [--no-paper] [--out startup]

Issue #16's startup targets, each measured in fresh processes:
- the first `simulate` call of the paper scene (2D L-shape r1, eG(1), h = 0.1, 10 steps)
  with no compilation cache ("cold"), and in a second process that finds the programs
  the first one left in a fresh cache directory ("cached");
- `jaxvisco paper --quick` (the README's first command after installing) likewise.
Scene construction and imports are timed separately from the first call; after it, a
second identical call, a call with another t_end (11 steps: the same default capacity,
12 slots, so no compilation) and the same with `max_steps=11` (an exact capacity: a new
program, what every new step count cost before capacities were bucketed). Writes
benchmarks/results/startup.json (or OUT.json; medians over the repeats, and every repeat).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

from common import machine, write_json  # noqa: I001

WORKER = r"""
import json, time
t0 = time.perf_counter()
import jax
jax.config.update("jax_enable_x64", True)
import jaxvisco as jv
if {cache!r}:
    jv.enable_compilation_cache({cache!r})
t1 = time.perf_counter()
scene = jv.scenes.lshape(dim=2, refinement=1)
t2 = time.perf_counter()
sol = jv.simulate(scene, jv.eG(1), t1=1.0, dt0=0.1)
t3 = time.perf_counter()
sol = jv.simulate(scene, jv.eG(1), t1=1.0, dt0=0.1)
t4 = time.perf_counter()
sol = jv.simulate(scene, jv.eG(1), t1=1.1, dt0=0.1)  # 11 steps: the same capacity (12) as 10
t5 = time.perf_counter()
sol = jv.simulate(scene, jv.eG(1), t1=1.1, dt0=0.1, max_steps=11)  # exact capacity: compiles (as before)
t6 = time.perf_counter()
print("RESULT " + json.dumps(dict(import_s=t1 - t0, scene_s=t2 - t1, first_call_s=t3 - t2, second_call_s=t4 - t3,
                                  other_t_end_s=t5 - t4, exact_capacity_s=t6 - t5, status=sol.status)))
"""


def _simulate(cache):
    env = dict(os.environ, JAXVISCO_CACHE_DIR="off")
    out = subprocess.run([sys.executable, "-c", WORKER.format(cache=cache)], capture_output=True, text=True,
                         check=True, env=env).stdout
    return json.loads(next(line[7:] for line in out.splitlines() if line.startswith("RESULT ")))


def _paper(cache, out):
    env = dict(os.environ, JAXVISCO_CACHE_DIR=cache or "off")
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "jaxvisco.cli", "paper", "--quick", "--out", out, "--overwrite"],
                   capture_output=True, text=True, check=True, env=env)
    return time.perf_counter() - t0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--no-paper", action="store_true")
    p.add_argument("--out", default="startup", help="results/OUT.json")
    a = p.parse_args(argv)
    mach = machine()
    runs = []
    for _ in range(a.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            cache = os.path.join(tmp, "cache")
            r = dict(cold=_simulate(None), filling=_simulate(cache), cached=_simulate(cache))
            if not a.no_paper:
                pcache = os.path.join(tmp, "paper-cache")
                r["paper_cold_s"] = _paper(None, os.path.join(tmp, "p0"))
                r["paper_filling_s"] = _paper(pcache, os.path.join(tmp, "p1"))
                r["paper_cached_s"] = _paper(pcache, os.path.join(tmp, "p2"))
        runs.append(r)
        print(json.dumps(r), flush=True)
    med = lambda f: statistics.median(f(r) for r in runs)  # noqa: E731
    summary = dict(first_call_cold_s=med(lambda r: r["cold"]["first_call_s"]),
                   first_call_cached_s=med(lambda r: r["cached"]["first_call_s"]),
                   second_call_s=med(lambda r: r["cold"]["second_call_s"]),
                   other_t_end_s=med(lambda r: r["cold"]["other_t_end_s"]),
                   exact_capacity_s=med(lambda r: r["cold"]["exact_capacity_s"]),
                   import_s=med(lambda r: r["cold"]["import_s"]), scene_s=med(lambda r: r["cold"]["scene_s"]))
    if not a.no_paper:
        summary.update(paper_quick_cold_s=med(lambda r: r["paper_cold_s"]),
                       paper_quick_cached_s=med(lambda r: r["paper_cached_s"]))
    summary["targets"] = {"first call cached <= 3 s": summary["first_call_cached_s"] <= 3.0,
                          "first call cold <= 6 s": summary["first_call_cold_s"] <= 6.0}
    if not a.no_paper:
        summary["targets"]["paper --quick cold <= 20 s"] = summary["paper_quick_cold_s"] <= 20.0
    print(json.dumps(summary, indent=1))
    write_json(f"{a.out}.json", dict(machine=mach, settings=dict(
        repeats=a.repeats, case="paper scene (2D L-shape r1), eG(1), h = 0.1, 10 steps; jaxvisco paper --quick",
        timing="each number from a fresh process; cold: no cache; cached: a second process on the cache the "
               "'filling' process wrote; medians over repeats"), summary=summary, runs=runs))


if __name__ == "__main__":
    main()
