"""Cost of a plain forward run at two revisions of jaxvisco, timed in alternation.

    python benchmarks/revision_cost.py --base REV [--case "2D r1,1,default,400"] [--rounds 3] [--out NAME]

Checks out REV into a temporary git worktree, builds its C++ extension in place, and then
runs `step_cost.py --case CASE` of each tree in turn (base, this tree, base, ...), each in
its own fresh process with JAX's persistent cache off, so both see the same machine load
round after round. Reports the medians over rounds of ms/step and of compile seconds, and
their ratios (this tree / base). Issue #17's budget for the one time loop is a ratio of
at most 1.05 in ms/step and a compile time no larger. Writes
benchmarks/results/revision_cost.json (or NAME.json) with the load averages before every run.
"""

import argparse
import json
import os
import pathlib
import shutil
import statistics
import subprocess
import sys
import tempfile
import zipfile

from common import machine, write_json  # noqa: I001

HERE = pathlib.Path(__file__).resolve().parent
REPO = HERE.parent


def _git(*args, cwd=REPO):
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def _build(tree):
    """Build the tree's wheel (pip: its own build requirements, isolated) and put its compiled
    extension next to the tree's sources, which are then used as they are."""
    out = tree.parent / "wheel"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "-w", str(out), str(tree)],
                   check=True, capture_output=True)
    with zipfile.ZipFile(next(out.glob("*.whl"))) as whl:
        for name in whl.namelist():
            if name.endswith(".so"):
                (tree / name).write_bytes(whl.read(name))


def _run(tree, case, timeout):
    env = dict(os.environ, JAXVISCO_CACHE_DIR="off", PYTHONPATH=str(tree))
    load = os.getloadavg()
    out = subprocess.run([sys.executable, "step_cost.py", "--case", case], cwd=tree / "benchmarks", env=env,
                         capture_output=True, text=True, timeout=timeout, check=True).stdout
    r = json.loads(next(line[7:] for line in out.splitlines() if line.startswith("RESULT ")))
    return dict(ms_per_step=r["ms_per_step"], ms_per_step_min=r["ms_per_step_min"], compile_s=r["compile_s"],
                newton_per_step=r["newton_per_step"], load_before=load)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--base", required=True, help="git revision to compare against")
    p.add_argument("--case", default="2D r1,1,default,400", help="step_cost.py case: scene,k,solver,steps")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per run")
    p.add_argument("--out", default="revision_cost", help="results/OUT.json")
    a = p.parse_args(argv)
    base_rev = _git("rev-parse", a.base)
    head_rev = _git("rev-parse", "HEAD")
    dirty = bool(_git("status", "--porcelain", "--untracked-files=no"))
    mach = machine()
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="jaxvisco-base-"))
    base_tree = tmp / "tree"
    _git("worktree", "add", "--detach", str(base_tree), base_rev)
    try:
        _build(base_tree)
        trees = {"base": base_tree, "head": REPO}
        runs = {"base": [], "head": []}
        for i in range(a.rounds):
            for name, tree in trees.items():
                r = _run(tree, a.case, a.timeout)
                runs[name].append(r)
                print(f"round {i + 1} {name}: {r['ms_per_step']:.2f} ms/step, compile {r['compile_s']:.1f} s, "
                      f"load {r['load_before'][0]:.2f}", flush=True)
    finally:
        _git("worktree", "remove", "--force", str(base_tree))
        shutil.rmtree(tmp, ignore_errors=True)

    def med(name, key):
        return statistics.median(r[key] for r in runs[name])

    summary = {key: dict(base=med("base", key), head=med("head", key), ratio=med("head", key) / med("base", key))
               for key in ("ms_per_step", "ms_per_step_min", "compile_s")}
    for key, s in summary.items():
        print(f"{key}: base {s['base']:.2f}, head {s['head']:.2f}, head/base {s['ratio']:.3f}")
    write_json(f"{a.out}.json", dict(
        machine=mach, base=base_rev, head=head_rev, head_has_uncommitted_changes=dirty, case=a.case,
        rounds=a.rounds, summary=summary, runs=runs,
        timing="each run a fresh process of step_cost.py --case (ms_per_step: median of 5 timed runs; compile_s: "
               "first call minus a timed call), trees alternating base/head every round, persistent cache off"))


if __name__ == "__main__":
    main()
