"""Scaling with problem size: the 3D L-shape (hex8 and tet4) by refinement.

    python benchmarks/scaling.py [--quick] [--max-refinement R] [--timeout S]

Each (element, refinement) runs in its own subprocess, so that its peak resident memory
(the RSS high-water mark, `ru_maxrss`, which includes XLA's buffers and compiled code) is
its own. Per case: eG(1) with h = 0.1 for a few steps; ms per step (after compilation),
Newton and Krylov iterations per step, compile time (first call minus a timed call), peak
RSS; with more than one step, the first step (it forms the tangent) and the later ones
(they reuse it) timed apart by a one-step call of the same compiled loop. Refinements grow until a case exceeds the per-case wall-clock limit or the DOF cap;
the log–log slope of ms/step against DOFs is fitted over the cases that ran. Writes
benchmarks/results/scaling.json and scaling.png.
"""

import argparse
import json
import subprocess
import sys
import time

from common import RESULTS, jv, lshape, machine, write_json  # noqa: I001

import numpy as np  # noqa: E402


def solver_for(preconditioner, precision="single", chord=None):
    """The solver of a case: the defaults with the block solve forced to `preconditioner`
    (and the multigrid's arithmetic to `precision`; `chord`: chord iterations per step,
    None for `NewtonKrylov`'s default, 0 for Newton–Krylov iterations only)."""
    extra = {} if chord is None else dict(chord=chord)
    return jv.NewtonKrylov(linear_solver=jv.GMRES(preconditioner=preconditioner, multigrid_precision=precision),
                           **extra)


def worker(element, refinement, steps, h, preconditioner="lu", precision="single", cycles=None, chord=None,
           counts_only=False):
    import resource

    from jaxvisco._solver import _amg

    if cycles is not None:  # read when the loop is traced
        _amg.CYCLES = cycles

    t0 = time.perf_counter()
    scene = lshape(3, refinement, element=element, mass="consistent")
    build_s = time.perf_counter() - t0
    dofs = int(scene.mesh.n_nodes * 3)

    solver = solver_for(preconditioner, precision, chord)

    def go(n=steps):  # n < steps: the same compiled loop (max_steps), n steps of it active
        return jv.simulate(scene, jv.eG(1), t1=n * h, dt0=h, saveat=jv.SaveAt(every=steps), max_steps=steps,
                           root_finder=solver)

    t0 = time.perf_counter()
    sol = go()
    first = time.perf_counter() - t0
    split = {}
    if counts_only:  # one call: the iteration counts and the memory, no step times
        wall = None
    else:
        t0 = time.perf_counter()
        sol = go()
        wall = time.perf_counter() - t0
    if steps > 1 and not counts_only:  # the first step (it forms the tangent) and the steps after it, which reuse it
        t0 = time.perf_counter()
        one = go(1)
        first_step = time.perf_counter() - t0
        split = dict(ms_first_step=1e3 * first_step, ms_per_later_step=1e3 * (wall - first_step) / (steps - 1),
                     first_step_status=one.status)
    its, kits = np.asarray(sol.newton_iterations), np.asarray(sol.krylov_iterations)
    out = dict(element=element, refinement=refinement, preconditioner=preconditioner, multigrid_precision=precision,
               multigrid_cycles=_amg.CYCLES, chord=solver.chord, dofs=dofs, n_cells=int(scene.mesh.cells.shape[0]),
               n_gamma=int(scene.gamma0.size // 9 * 6), steps=steps, h=h, status=sol.status,
               **({} if counts_only else dict(ms_per_step=1e3 * wall / steps, compile_s=first - wall)),
               first_call_s=first, build_s=build_s,
               newton_per_step=float(its.mean()), krylov_per_step=float(kits.mean()),
               chord_per_step=float(np.asarray(sol.chord_iterations).mean()),
               krylov_per_newton=float(kits.sum() / max(its.sum(), 1)),
               newton_by_step=its.tolist(), krylov_by_step=kits.tolist(),
               peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, **split, **_device_memory())
    print("RESULT " + json.dumps(out), flush=True)


def _device_memory():
    """The device the case ran on and, where its runtime reports one (GPUs), the peak of
    the device memory its buffers held (`memory_stats()['peak_bytes_in_use']`)."""
    import jax

    dev = jax.devices()[0]
    out = dict(device=f"{dev.platform}: {getattr(dev, 'device_kind', '')}")
    stats = dev.memory_stats() if hasattr(dev, "memory_stats") else None
    if stats and "peak_bytes_in_use" in stats:
        out["device_peak_mb"] = stats["peak_bytes_in_use"] / 2**20
    return out


def run_case(element, refinement, steps, h, timeout, preconditioner="lu", precision="single", cycles=None,
             chord=None, counts_only=False):
    cmd = [sys.executable, __file__, "--worker", element, str(refinement), str(steps), str(h), preconditioner, precision,
           str(cycles or 0), str(-1 if chord is None else chord), str(int(counts_only))]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        return dict(element=element, refinement=refinement, status=f"stopped at the {timeout:.0f} s limit",
                    wall_s=time.perf_counter() - t0)
    for line in out.splitlines():
        if line.startswith("RESULT "):
            r = json.loads(line[7:])
            r["wall_s"] = time.perf_counter() - t0
            return r
    return dict(element=element, refinement=refinement, status="error", wall_s=time.perf_counter() - t0,
                output_tail=out[-2000:])


def slope(rows, key="ms_per_step"):
    pts = [(r["dofs"], r[key]) for r in rows if key in r and r.get(key) and r["dofs"] >= 1000]
    if len(pts) < 2:
        pts = [(r["dofs"], r[key]) for r in rows if key in r and r.get(key)]
    if len(pts) < 2:
        return None
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    for el in dict.fromkeys(r["element"] for r in rows):
        rs = [r for r in rows if r["element"] == el and "dofs" in r]
        if not rs:
            continue
        d = [r["dofs"] for r in rs]
        axes[0].loglog(d, [r["ms_per_step"] for r in rs], "o-", label=el)
        axes[1].loglog(d, [r["compile_s"] for r in rs], "o-", label=el)
        axes[2].loglog(d, [r["peak_rss_mb"] for r in rs], "o-", label=el)
    for ax, t in zip(axes, ("ms per step (eG(1), h = 0.1)", "compile time [s]", "peak RSS [MB]")):
        ax.set_xlabel("DOFs (positions)")
        ax.set_title(t, fontsize=9)
        ax.grid(True, which="both", lw=0.3)
        ax.legend()
    if rows:
        d = np.array(sorted({r["dofs"] for r in rows if "dofs" in r}), dtype=float)
        if d.size:
            ms0 = min(r["ms_per_step"] for r in rows if "dofs" in r and r["dofs"] == d[0])
            axes[0].loglog(d, ms0 * (d / d[0]) ** 1.2, "k:", lw=0.8, label="DOFs^1.2")
            axes[0].legend()
    fig.suptitle("3D L-shape scaling, 2-core CPU, one benchmark at a time", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}", flush=True)


def main(argv=None):
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--worker":
        element, r, steps, h, preconditioner, precision, cycles, *rest = sys.argv[2:]
        chord, counts_only = (rest + ["-1", "0"][len(rest):])[:2]  # optional: default chord, timed
        worker(element, int(r), int(steps), float(h), preconditioner, precision, int(cycles) or None,
               None if int(chord) < 0 else int(chord), bool(int(counts_only)))
        return
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="hex8 refinement 1 and 2 only")
    p.add_argument("--max-refinement", type=int, default=None)
    p.add_argument("--refinements", default=None,
                   help="comma-separated refinements to run (instead of 1 .. --max-refinement)")
    p.add_argument("--elements", default="hex8,tet4")
    p.add_argument("--timeout", type=float, default=None, help="wall-clock limit of one case [s]")
    p.add_argument("--max-dofs", type=int, default=120_000)
    p.add_argument("--steps", type=int, default=None)
    p.add_argument("--out", default="scaling")
    p.add_argument("--preconditioner", default="lu", choices=("lu", "amg"),
                   help="block solve of GMRES's preconditioner: host LU (default) or multigrid")
    p.add_argument("--multigrid-precision", default="single", choices=("single", "double"),
                   help="arithmetic of the multigrid's cycles (GMRES(multigrid_precision=))")
    p.add_argument("--cycles", type=int, default=None,
                   help="W-cycles per application of the multigrid preconditioner (default: _amg.CYCLES)")
    p.add_argument("--chord", type=int, default=None,
                   help="chord iterations per step (default: NewtonKrylov's; 0: Newton–Krylov iterations only, "
                        "which measures the Krylov iterations per Newton iteration at every refinement)")
    p.add_argument("--counts-only", action="store_true",
                   help="run each case once (compile included) for its iteration counts and memory, no step times")
    p.add_argument("--append", action="store_true", help="keep the rows of other elements already in the file")
    p.add_argument("--memory-fraction", type=float, default=0.5,
                   help="skip a case whose peak RSS, extrapolated from the smaller ones, exceeds this fraction "
                        "of the available memory (the machine is shared)")
    a = p.parse_args(argv)
    max_r = a.max_refinement or (2 if a.quick else 8)
    timeout = a.timeout or (150.0 if a.quick else 900.0)
    steps = a.steps or (3 if a.quick else 5)
    elements = ["hex8"] if a.quick else a.elements.split(",")
    rows = []
    data = dict(machine=machine(), settings=dict(
        integrator="eG(1)", h=0.1, steps=steps, solver=f"NewtonKrylov(linear_solver=GMRES(preconditioner={a.preconditioner!r}, "
                                      f"multigrid_precision={a.multigrid_precision!r})"
                                      + ("" if a.chord is None else f", chord={a.chord}") + ")", mass="consistent",
        per_case_timeout_s=timeout, max_dofs=a.max_dofs, quick=a.quick,
        peak_memory="ru_maxrss of the subprocess that ran the case (RSS high-water mark)"), rows=rows)
    if a.append and (RESULTS / f"{a.out}.json").exists():
        old = json.loads((RESULTS / f"{a.out}.json").read_text())
        rows += [r for r in old["rows"] if r["element"] not in elements]
        data["settings"]["earlier_rows_from"] = old["machine"]["date"]
    for el in elements:
        for r in ([int(x) for x in a.refinements.split(",")] if a.refinements else range(1, max_r + 1)):
            dofs = lshape_dofs(el, r)
            if dofs > a.max_dofs:
                print(f"{el} r{r}: {dofs} DOFs > cap {a.max_dofs}, stop", flush=True)
                break
            est = _rss_estimate([x for x in rows if x["element"] == el and "peak_rss_mb" in x], dofs)
            avail = _available_mb()
            if est is not None and avail is not None and est > a.memory_fraction * avail:
                msg = (f"skipped: peak RSS extrapolated to {est:.0f} MB > {a.memory_fraction:g} x the "
                       f"{avail:.0f} MB available on this shared machine")
                rows.append(dict(element=el, refinement=r, dofs=dofs, status=msg))
                print(f"{el} r{r}: {msg}", flush=True)
                break
            res = run_case(el, r, steps, 0.1, timeout, a.preconditioner, a.multigrid_precision, a.cycles, a.chord,
                           a.counts_only)
            res.setdefault("dofs", dofs)
            rows.append(res)
            print(json.dumps(res), flush=True)
            write_json(f"{a.out}.json", data)
            if "newton_per_step" not in res:
                print(f"{el} r{r}: {res['status']}; larger refinements skipped", flush=True)
                break
    for el in dict.fromkeys(r["element"] for r in rows):
        rs = [r for r in rows if r["element"] == el and "ms_per_step" in r]
        data.setdefault("slope_ms_per_step_vs_dofs", {})[el] = slope(rs)
        data.setdefault("slope_compile_vs_dofs", {})[el] = slope(rs, "compile_s")
        data.setdefault("dof_range", {})[el] = [min((r["dofs"] for r in rs), default=None),
                                                max((r["dofs"] for r in rs), default=None)]
        kn = [r["krylov_per_newton"] for r in sorted(rows, key=lambda r: r["dofs"])
              if r["element"] == el and r.get("newton_per_step")]
        # #19's target: Krylov iterations per Newton iteration, largest refinement over smallest
        data.setdefault("krylov_per_newton_growth", {})[el] = kn[-1] / kn[0] if len(kn) > 1 else None
    write_json(f"{a.out}.json", data)
    if any("ms_per_step" in r for r in rows):
        plot([r for r in rows if "ms_per_step" in r], RESULTS / f"{a.out}.png")


def _rss_estimate(rows, dofs):
    """Linear extrapolation of peak RSS in DOFs from the two largest cases run."""
    rs = sorted(rows, key=lambda r: r["dofs"])[-2:]
    if len(rs) < 2:
        return None
    (d0, m0), (d1, m1) = ((r["dofs"], r["peak_rss_mb"]) for r in rs)
    return m1 + (m1 - m0) / (d1 - d0) * (dofs - d1)


def _available_mb():
    try:
        for line in open("/proc/meminfo"):
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def lshape_dofs(element, r):
    return int(jv.lshape_mesh(dim=3, refinement=r, cell_type=element).n_nodes * 3)


if __name__ == "__main__":
    main()
