"""What a user waits for before a fit's first answer: whole processes, wall clock.

    python benchmarks/identify_startup.py [--repeats 3] [--baseline PATH] [--out identify_startup.json]

Cases, each a fresh Python process (interpreter start, imports, tracing, compiling,
running; one at a time):

- `example_cold`: `examples/identify_viscosity.py --quick` (its synthetic data and two
  fits of the 2D L-shape's viscosities), no compilation cache (issue #59's "cold");
- `example_first` and `example_second`: the same with the persistent cache on, in a new
  cache directory (the first process fills it) and then again (the second process is
  served by it);
- `cli_first` and `cli_second`: `jaxvisco identify examples/fit/fit.toml` (the 3D
  specimen's relaxation and cyclic tests, three parameters), the same way.

Each case is repeated `--repeats` times (a new cache directory per repeat) and the median
reported. `--baseline PATH`: the same cases also with the jaxvisco of another checkout
(put first on `PYTHONPATH`), alternating with this one in each repeat, so that both see
the same machine state.
"""

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

from common import machine, write_json  # noqa: I001

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
EXAMPLE = ("{python}", "{root}/examples/identify_viscosity.py", "--quick", "--out", "{tmp}/out")
CLI = ("{python}", "-m", "jaxvisco.cli", "identify", "{tmp}/fit/fit.toml", "--report", "{tmp}/fit.json",
       "--plot", "{tmp}/fit.png")
SETUP = "import sys, jaxvisco; jaxvisco.enable_compilation_cache(sys.argv[1]); sys.argv = sys.argv[2:]; "


def _wall(cmd, root, cache=None):
    """Seconds a fresh process of `cmd` takes (with the persistent cache in `cache`)."""
    with tempfile.TemporaryDirectory(prefix="jaxvisco-startup-") as tmp:
        shutil.copytree(os.path.join(root, "examples", "fit"), os.path.join(tmp, "fit"))
        argv = [a.format(python=sys.executable, root=root, tmp=tmp) for a in cmd]
        if cache is not None:  # the same command, the cache turned on first
            if argv[1] == "-m":
                argv = [argv[0], "-c", SETUP + f"import runpy; runpy.run_module({argv[2]!r}, run_name='__main__')",
                        cache, argv[2]] + argv[3:]
            else:
                argv = [argv[0], "-c", SETUP + f"import runpy; runpy.run_path({argv[1]!r}, run_name='__main__')",
                        cache] + argv[1:]
        env = dict(os.environ, PYTHONPATH=root, JAXVISCO_CACHE_DIR=cache or "off", MPLBACKEND="Agg")
        t0 = time.perf_counter()
        subprocess.run(argv, cwd=tmp, env=env, check=True, capture_output=True)
        return time.perf_counter() - t0


def _cases(root):
    """Every case once, for the jaxvisco in `root`: case name -> seconds."""
    out = {"example_cold": _wall(EXAMPLE, root)}
    for name, cmd in (("example", EXAMPLE), ("cli", CLI)):
        cache = tempfile.mkdtemp(prefix="jaxvisco-startup-cache-")
        try:
            out[f"{name}_first"] = _wall(cmd, root, cache)
            out[f"{name}_second"] = _wall(cmd, root, cache)
        finally:
            shutil.rmtree(cache, ignore_errors=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline", default=None, help="another checkout to measure alongside")
    ap.add_argument("--out", default="identify_startup")
    a = ap.parse_args(argv)
    roots = {"this": ROOT} if a.baseline is None else {"this": ROOT, "baseline": os.path.abspath(a.baseline)}
    info = machine()  # the load before the runs
    commits = {label: subprocess.run(["git", "-C", root, "rev-parse", "HEAD"], capture_output=True,
                                     text=True).stdout.strip() for label, root in roots.items()}
    runs = {label: [] for label in roots}
    for i in range(a.repeats):
        for label, root in roots.items():
            runs[label].append(_cases(root))
            print(i, label, {k: round(v, 1) for k, v in runs[label][-1].items()}, flush=True)
    data = dict(machine=info, repeats=a.repeats, roots=roots, commits=commits, cases={})
    for label, rows in runs.items():
        data["cases"][label] = {k: dict(median_s=statistics.median(r[k] for r in rows), all_s=[r[k] for r in rows])
                                for k in rows[0]}
    write_json(f"{a.out}.json", data)


if __name__ == "__main__":
    main()
