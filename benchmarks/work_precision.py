"""Work–precision: wall time against error on the 2D L-shape, jaxvisco against ODE peers.

    python benchmarks/work_precision.py [--quick] [--refinements 1,3] [--t-end 10] [--adaptive-only]

The 2D L-shape (refinement 1 and 2 by default; issue #18 asks for 1 and 3) with a *lumped*
mass matrix for every method (the peers need a sparse Jacobian, and with the consistent
mass ẋ = M⁻¹p makes it dense), over t ∈ [0, T]. Error = max(relative error of the
positions at T, relative error of H(T)) against a reference: eG(3) with a tiny step,
cross-checked by scipy Radau at rtol 1e-12 (or, `--check eG-2h`, by eG(3) at twice the
step; their difference is reported). The relative error of the cumulative dissipated
energy D(T) is reported beside it (`error_D`; jaxvisco runs only: the ODE peers do not
integrate D, so theirs is null). Methods: cG(1..3), eG(1..3), Newmark, Midpoint over a
range of constant steps; eG(1..3) with error-controlled steps (`PIDController`,
"eG(k) adaptive") over rtol = atol; scipy `solve_ivp` Radau and BDF (exact sparse
Jacobian from `jaxvisco.semidiscrete`), diffrax Kvaerno5 and Kvaerno3 (PID step control,
their default root finder: a dense Jacobian by forward AD, LU by lineax — diffrax has no
sparse path) over the same rtol = atol. Wall time is measured after compilation (median
of repeats); compile time is reported separately. The summary (`adaptive_summary`) gives,
at errors 1e-3, 1e-4 and 1e-6 (log-log interpolation along each curve), the wall time of
the best adaptive eG and each peer's wall time over it. Writes
benchmarks/results/work_precision.json and work_precision.png.
"""

import argparse
import functools
import json
import math
import pathlib
import subprocess
import sys
import tempfile
import time

from common import RESULTS, jv, lshape, machine, rel, timed, write_json  # noqa: I001
from common import schemes as all_schemes  # noqa: I001

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

TARGET = 1e-6
TARGETS = (1e-3, 1e-4, 1e-6)  # the errors of the adaptive summary
PEERS = ("scipy", "diffrax")
ADAPTIVE = " adaptive"  # suffix of the error-controlled jaxvisco methods


def _errors(x, H, ref):
    ex = rel(x, ref["x"])
    eH = abs(float(H) - ref["H"]) / abs(ref["H"])
    return ex, eH, max(ex, eH)


def _error_D(D, ref):
    """Relative error of the cumulative dissipated energy at T (None without a reference D)."""
    if ref.get("D") is None or not np.isfinite(ref["D"]):
        return None
    return abs(float(D) - ref["D"]) / abs(ref["D"])


def run_jaxvisco(scene, name, scheme, hs, T, ref, cap, budget_s, repeats):
    rows = []
    for h in hs:
        n = int(round(T / h))

        def go():
            return jv.simulate(scene, scheme, t1=T, dt0=h, saveat=jv.SaveAt(every=cap), max_steps=cap, throw=False)

        sol, first, wall, times = timed(go, repeats=repeats, budget_s=budget_s / 4)
        ok = sol.status == "done"
        ex, eH, e = _errors(sol.x[-1], sol.energy[-1], ref) if ok else (math.nan,) * 3
        eD = _error_D(sol.dissipated[-1], ref) if ok else math.nan
        row = dict(method=name, family="jaxvisco", h=h, steps=n, status=sol.status, error_x=ex, error_H=eH, error=e,
                   error_D=eD, dissipated=float(sol.dissipated[-1]), wall_s=wall, times_s=times, compile_s=first - wall,
                   newton_per_step=float(np.mean(np.asarray(sol.newton_iterations))),
                   krylov_per_step=float(np.mean(np.asarray(sol.krylov_iterations))))
        print(f"  {name:9s} h={h:<8g} err={e:.3e} (x {ex:.2e}, H {eH:.2e}, D {eD if eD is not None else math.nan:.2e}) "
              f"wall={wall:.3f}s "
              f"first={first:.1f}s {sol.status}", flush=True)
        rows.append(row)
        if wall > budget_s:
            print(f"  {name}: {wall:.1f}s > budget {budget_s}s, smaller steps skipped", flush=True)
            break
    return rows


def run_adaptive(scene, name, scheme, tols, T, ref, cap, budget_s, repeats):
    """eG(k) with error-controlled steps (`PIDController(rtol=tol, atol=tol)`, first step
    tried: a hundredth of the run), loosest tolerance first. A new tolerance does not
    compile again (the tolerances are array leaves): the compile time is that of the
    first one. Tighter tolerances are skipped once a run after the loosest one takes
    longer than the budget."""
    rows, over = [], False
    method = name + ADAPTIVE
    for i, tol in enumerate(tols):
        if over:
            rows.append(dict(method=method, family="jaxvisco adaptive", scheme=name, rtol=tol, atol=tol,
                             status="skipped (budget)", error=math.nan, error_x=math.nan, error_H=math.nan,
                             error_D=math.nan, wall_s=math.nan))
            continue
        ctrl = jv.PIDController(rtol=tol, atol=tol)

        def go():
            return jv.simulate(scene, scheme, 0.0, T, None, stepsize_controller=ctrl, saveat=jv.SaveAt(every=cap),
                               max_steps=cap, throw=False)

        sol, first, wall, times = timed(go, repeats=repeats, budget_s=budget_s / 4)
        ok = sol.status == "done"
        ex, eH, e = _errors(sol.x[-1], sol.energy[-1], ref) if ok else (math.nan,) * 3
        eD = _error_D(sol.dissipated[-1], ref) if ok else math.nan
        hs = np.asarray(sol.step_h)
        row = dict(method=method, family="jaxvisco adaptive", scheme=name, rtol=tol, atol=tol,
                   steps=int(sol.n_steps), rejections=int(np.sum(np.asarray(sol.rejections))), status=sol.status,
                   error_x=ex, error_H=eH, error=e, error_D=eD, dissipated=float(sol.dissipated[-1]),
                   wall_s=wall, times_s=times, first_call_s=first,
                   newton_iterations=int(np.sum(np.asarray(sol.newton_iterations))),
                   chord_iterations=int(np.sum(np.asarray(sol.chord_iterations))),
                   krylov_iterations=int(np.sum(np.asarray(sol.krylov_iterations))),
                   h_min=float(hs.min()) if hs.size else None, h_median=float(np.median(hs)) if hs.size else None,
                   h_max=float(hs.max()) if hs.size else None, max_steps=cap)
        if i == 0:
            row["compile_s"] = first - wall  # the program serves every tolerance
        print(f"  {method:15s} tol={tol:<8g} err={e:.3e} (x {ex:.2e}, H {eH:.2e}, "
              f"D {eD if eD is not None else math.nan:.2e}) wall={wall:.3f}s first={first:.1f}s "
              f"steps={row['steps']} rej={row['rejections']} newton={row['newton_iterations']} "
              f"chord={row['chord_iterations']} {sol.status}", flush=True)
        rows.append(row)
        # Not after the loosest tolerance: its long steps can cost more Newton iterations
        # than the tighter runs (eG(2) at 1e-2 on r3: 296 s, 39 rejections, against 10-20 s).
        if wall > budget_s and i > 0:
            print(f"  {method}: {wall:.1f}s > budget {budget_s}s, tighter tolerances skipped", flush=True)
            over = True
    return rows


def run_scipy(ode, method, tols, T, ref, budget_s, repeats):
    rows = []
    for tol in tols:
        def go():
            return solve_ivp(ode.fun, (0.0, T), ode.y0, method=method, jac=ode.jac, rtol=tol, atol=tol)

        r, first, wall, times = timed(go, repeats=repeats, budget_s=budget_s / 4)
        y = r.y[:, -1]
        ok = bool(r.success)
        ex, eH, e = _errors(ode.unpack(y).x, ode.energy(y), ref) if ok else (math.nan,) * 3
        rows.append(dict(method=f"scipy {method}", family="peer", rtol=tol, atol=tol, steps=int(r.t.size - 1),
                         nfev=int(r.nfev), njev=int(r.njev), nlu=int(r.nlu), status="done" if ok else r.message,
                         error_x=ex, error_H=eH, error=e, error_D=None, wall_s=wall, times_s=times))
        print(f"  scipy {method:5s} tol={tol:<8g} err={e:.3e} wall={wall:.3f}s steps={r.t.size - 1} "
              f"nfev={r.nfev} nlu={r.nlu}", flush=True)
        if wall > budget_s:
            print(f"  scipy {method}: {wall:.1f}s > budget {budget_s}s, tighter tolerances skipped", flush=True)
            break
    return rows


def run_diffrax(ode, name, tols, T, ref, budget_s, repeats, worker_timeout_s, refinement):
    """diffrax in a subprocess (its implicit solvers can take far longer than the budget;
    a subprocess can be stopped at a wall-clock limit, a running XLA program cannot)."""
    with tempfile.TemporaryDirectory() as tmp:
        ref_path = pathlib.Path(tmp) / "ref.npz"
        np.savez(ref_path, x=ref["x"], H=ref["H"])
        cmd = [sys.executable, __file__, "--diffrax-worker", name, "--refinements", str(refinement), "--t-end", str(T),
               "--tols", ",".join(map(str, tols)), "--budget", str(budget_s), "--repeats", str(repeats),
               "--ref", str(ref_path)]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
        rows, t0 = [], time.perf_counter()
        try:
            out, _ = proc.communicate(timeout=worker_timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
        timed_out = time.perf_counter() - t0 >= worker_timeout_s
        probe = None
        for line in out.splitlines():
            if line.startswith("ROW "):
                rows.append(json.loads(line[4:]))
            elif line.startswith("PROBE "):
                probe = json.loads(line[6:])
            else:
                print(line, flush=True)
        done = {r["rtol"] for r in rows}
        for tol in tols:
            if tol not in done:
                rows.append(dict(method=f"diffrax {name}", family="peer", rtol=tol, atol=tol,
                                 status=(f"not finished: worker stopped at the {worker_timeout_s:.0f} s limit"
                                         if timed_out else "skipped (budget)"),
                                 error=math.nan, error_x=math.nan, error_H=math.nan, error_D=None, wall_s=math.nan,
                                 probe=probe))
                if timed_out:
                    print(f"  diffrax {name} tol={tol:g}: stopped at the {worker_timeout_s:.0f} s limit", flush=True)
                    timed_out = False  # the tighter ones were never started
        return rows


def diffrax_worker(name, refinement, T, tols, budget_s, repeats, ref_path, max_steps=1_000_000):
    import diffrax as dfx

    z = np.load(ref_path)
    ref = dict(x=z["x"], H=float(z["H"]))
    ode = jv.semidiscrete(lshape(2, refinement, mass="lumped"))
    solver = {"Kvaerno5": dfx.Kvaerno5(), "Kvaerno3": dfx.Kvaerno3(), "Tsit5": dfx.Tsit5()}[name]
    term = dfx.ODETerm(ode.vector_field)

    # compiled with jaxvisco's XLA options, as jaxvisco's own programs and scipy's
    # right-hand side (`ode.rhs`) are: with XLA's defaults the right-hand side costs
    # 2.8x as much at refinement 1 (66 against 24 us; `jaxvisco.compiler_options`)
    @functools.partial(jax.jit, compiler_options=jv.compiler_options())
    def solve(y0, tol, t1):
        s = dfx.diffeqsolve(term, solver, 0.0, t1, 1e-3, y0, stepsize_controller=dfx.PIDController(rtol=tol, atol=tol),
                            saveat=dfx.SaveAt(t1=True), max_steps=max_steps, throw=False)
        return s.ys[-1], s.stats["num_steps"], s.stats["num_rejected_steps"], s.result == dfx.RESULTS.successful

    y0 = jnp.asarray(ode.y0)
    t0 = time.perf_counter()
    compiled = solve.lower(y0, tols[0], T).compile()
    compile_s = time.perf_counter() - t0
    print(f"  diffrax {name}: compiled in {compile_s:.1f}s", flush=True)
    # A probe over the first 1 % of the interval at the loosest tolerance: the cost of one
    # step, recorded even when the full runs do not finish within the worker's time limit.
    t0 = time.perf_counter()
    _, steps, rejected, _ = jax.block_until_ready(compiled(y0, tols[0], T / 100))
    probe_s = time.perf_counter() - t0
    probe = dict(t1=T / 100, rtol=tols[0], wall_s=probe_s, steps=int(steps), rejected=int(rejected),
                 s_per_attempted_step=probe_s / max(int(steps) + int(rejected), 1))
    print(f"  diffrax {name} probe to t={T / 100:g} at tol {tols[0]:g}: {probe_s:.1f}s, {int(steps)} steps "
          f"+ {int(rejected)} rejected", flush=True)
    print("PROBE " + json.dumps(probe), flush=True)
    for tol in tols:
        out, first, wall, times = timed(lambda: jax.block_until_ready(compiled(y0, tol, T)), repeats=repeats,
                                        budget_s=budget_s / 4)
        y, steps, rejected, ok = out
        ok = bool(ok)
        ex, eH, e = _errors(ode.unpack(y).x, ode.energy(y), ref) if ok else (math.nan,) * 3
        row = dict(method=f"diffrax {name}", family="peer", rtol=tol, atol=tol, steps=int(steps),
                   rejected=int(rejected), status="done" if ok else "failed", error_x=ex, error_H=eH, error=e,
                   error_D=None, wall_s=wall, times_s=times, compile_s=compile_s,
                   jacobian="explicit" if name == "Tsit5" else "dense (forward AD), lineax LU")
        print(f"  diffrax {name} tol={tol:<8g} err={e:.3e} wall={wall:.3f}s steps={int(steps)}", flush=True)
        print("ROW " + json.dumps(row), flush=True)
        if wall > budget_s:
            print(f"  diffrax {name}: {wall:.1f}s > budget {budget_s}s, tighter tolerances skipped", flush=True)
            break


def front(rows):
    """The work–precision front of one method's runs: those that no other run beats in both
    error and wall time, ordered by decreasing error. A dominated run is one a user would
    never choose: eG(3) on r3 at h = 1 took 2.84 s for an error of 1.4e-4 (its steps fall
    back to Newton–Krylov) where h = 0.4 took 1.55 s for 4.1e-5; scipy Radau on r2 and r3
    took longer at rtol 1e-3 than at 1e-4."""
    ok = [r for r in rows if r.get("error") is not None and np.isfinite(r["error"]) and r["error"] > 0]
    keep = [r for r in ok if not any(o is not r and o["error"] <= r["error"] and o["wall_s"] <= r["wall_s"]
                                     and (o["error"] < r["error"] or o["wall_s"] < r["wall_s"]) for o in ok)]
    return sorted(keep, key=lambda r: -r["error"])


def interpolate_at(rows, target=TARGET):
    """Wall time at `target` error, log–log interpolated between the consecutive runs of
    the work–precision `front` whose errors bracket it; None where the front does not reach
    across the target (every run of the method more accurate, or every one less). Before
    session 31 the curve was every run in the order of its setting, so that a dominated
    run could bracket the target: the r3 summary read eG(3) at 1e-4 as 2.44 s, between
    h = 1 (2.84 s) and h = 0.4 (1.55 s, error 4.1e-5)."""
    pts = [(r["wall_s"], r["error"]) for r in front(rows)]
    for (w0, e0), (w1, e1) in zip(pts, pts[1:]):
        if (e0 - target) * (e1 - target) <= 0 and e0 != e1:
            s = (math.log(target) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(w0) + s * (math.log(w1) - math.log(w0)))
    return None


def at_most(rows, target):
    """Where every run of a method's front is more accurate than `target`: the wall time of
    its cheapest run, an upper bound on the time the method needs for an error of at most
    `target` (its curve does not reach up to the target, so nothing is interpolated).
    None otherwise."""
    f = front(rows)
    return f[0]["wall_s"] if f and f[0]["error"] < target else None


def compare(runs):
    at = {m: interpolate_at([x for x in runs if x["method"] == m]) for m in dict.fromkeys(x["method"] for x in runs)}
    jv_best = {m: w for m, w in at.items() if w is not None and not m.startswith(("scipy", "diffrax"))}
    best = min(jv_best, key=jv_best.get) if jv_best else None
    speedup = {m: (w / jv_best[best] if (w is not None and best) else None)
               for m, w in at.items() if m.startswith(("scipy", "diffrax"))}
    return at, best, speedup


def _reach_note(rows, target):
    """Why a curve has no wall time at `target`."""
    ok = [r["error"] for r in rows if r.get("error") is not None and np.isfinite(r["error"]) and r["error"] > 0]
    if not ok:
        return "no run finished: " + "; ".join(dict.fromkeys(str(r.get("status")) for r in rows))
    f = [r["error"] for r in front(rows)]
    if len(f) < len(ok):
        return (f"its front's errors ({min(f):.2g} to {max(f):.2g}; {len(ok) - len(f)} slower and less accurate runs "
                f"left out) do not bracket {target:g}")
    return f"its errors ({min(ok):.2g} to {max(ok):.2g}) do not bracket {target:g}"


def adaptive_summary(runs, targets=TARGETS):
    """At each target error: the wall time of the best adaptive eG (least interpolated wall
    time among eG(k) adaptive) and every other curve's wall time over it (> 1: the adaptive
    eG is faster): each peer, the best constant-step eG, and the best constant-step
    jaxvisco scheme of any family."""
    methods = list(dict.fromkeys(r["method"] for r in runs))
    rows_of = {m: [r for r in runs if r["method"] == m] for m in methods}
    out = {}
    for target in targets:
        at = {m: interpolate_at(rows_of[m], target) for m in methods}
        adaptive = {m: w for m, w in at.items() if m.endswith(ADAPTIVE) and w is not None}
        fixed_eg = {m: w for m, w in at.items() if m.startswith("eG") and not m.endswith(ADAPTIVE) and w is not None}
        fixed_any = {m: w for m, w in at.items() if not m.startswith(PEERS) and not m.endswith(ADAPTIVE)
                     and w is not None}
        best = min(adaptive, key=adaptive.get) if adaptive else None
        wb = adaptive.get(best)
        best_eg = min(fixed_eg, key=fixed_eg.get) if fixed_eg else None
        best_any = min(fixed_any, key=fixed_any.get) if fixed_any else None
        others = {m: at[m] for m in methods if m.startswith(PEERS)}
        others["best fixed-step eG"] = fixed_eg.get(best_eg)
        others["best fixed-step jaxvisco"] = fixed_any.get(best_any)
        ratio = {m: (w / wb if (w is not None and wb) else None) for m, w in others.items()}
        notes = {m: _reach_note(rows_of[m], target) for m in methods if at[m] is None}
        bounds = {m: at_most(rows_of[m], target) for m in methods if at[m] is None}
        out[f"{target:g}"] = dict(best_adaptive_eG=best, wall_s=wb, best_fixed_eG=best_eg, best_fixed_jaxvisco=best_any,
                                  ratio_to_best_adaptive=ratio, wall_at_error_s=at, no_value=notes,
                                  wall_at_most_s={m: w for m, w in bounds.items() if w is not None})
    return out


def print_adaptive_summary(key, summ):
    print(f"{key}: wall time at error e of the best adaptive eG, and each curve's wall time over it", flush=True)
    for t, d in summ.items():
        head = (f"  e={t}: best adaptive {d['best_adaptive_eG']} {d['wall_s']:.3g}s" if d["wall_s"] else
                f"  e={t}: no adaptive eG curve reaches it")
        which = {"best fixed-step eG": d["best_fixed_eG"], "best fixed-step jaxvisco": d["best_fixed_jaxvisco"]}
        parts = [(f"{m}" + (f" ({which[m]})" if which.get(m) else "") + (f" {r:.2f}x" if r is not None else " n/a"))
                 for m, r in d["ratio_to_best_adaptive"].items()]
        bounds = d.get("wall_at_most_s") or {}
        tail = ("; every run more accurate than e, cheapest: " + ", ".join(f"{m} {w:.3g}s" for m, w in bounds.items())
                if bounds else "")
        print(head + "; " + ", ".join(parts) + tail, flush=True)


def merge(names, out):
    """Merge runs of the same scenes measured in separate processes (same settings). A
    scene new to the first file is added; a method measured in a later file replaces all
    of that method's rows in the earlier ones (the merge notes which)."""
    datas = [json.loads((RESULTS / f"{n}.json").read_text()) for n in names]
    data = datas[0]
    data["merged_from"] = {n: dict(machine=d["machine"], settings=d["settings"],
                                   references={k: v["reference"] for k, v in d["scenes"].items()})
                           for n, d in zip(names, datas)}
    for name, d in zip(names[1:], datas[1:]):
        for key, sc in d["scenes"].items():
            if key not in data["scenes"]:
                data["scenes"][key] = sc
                continue
            # A method measured in a later file replaces every row of it in the earlier ones
            # (a re-measurement, or runs that did not finish there).
            measured = {r["method"] for r in sc["runs"] if np.isfinite(r.get("error", np.nan))}
            kept = [r for r in data["scenes"][key]["runs"] if r["method"] not in measured]
            if len(kept) < len(data["scenes"][key]["runs"]):
                data["scenes"][key].setdefault("notes", []).append(
                    f"rows of {sorted(measured & {r['method'] for r in data['scenes'][key]['runs']})} replaced by "
                    f"the runs of a separate process ({name})")
            data["scenes"][key]["runs"] = kept + sc["runs"]
            data["scenes"][key].setdefault("other_references", []).append(sc["reference"])
    _derive(data, out)


def _derive(data, out):
    """Recompute a results file's summaries (wall times at the target errors, ratios) from
    its runs, and write it and its figure as results/`out`."""
    for key, sc in data["scenes"].items():
        sc["wall_at_target_s"], sc["best_jaxvisco"], sc["speedup_at_target"] = compare(sc["runs"])
        sc["adaptive_summary"] = adaptive_summary(sc["runs"])
        print(f"{key}: best jaxvisco {sc['best_jaxvisco']}, speedups {sc['speedup_at_target']}", flush=True)
        print_adaptive_summary(key, sc["adaptive_summary"])
    data["adaptive_summary"] = {k: sc["adaptive_summary"] for k, sc in data["scenes"].items()}
    write_json(f"{out}.json", data, stamp_end=False)
    plot(data, RESULTS / f"{out}.png")


def _style(m):
    """Line style of a method: constant-step jaxvisco solid, adaptive eG dashed (same colour
    as the constant-step eG(k)), peers dotted."""
    base = m[:-len(ADAPTIVE)] if m.endswith(ADAPTIVE) else m
    color = {"cG(1)": "#f4a582", "cG(2)": "#92c5de", "cG(3)": "#a6dba0", "eG(1)": "#d6604d", "eG(2)": "#2166ac",
             "eG(3)": "#1b7837", "Newmark": "#bf812d", "Midpoint": "#80cdc1", "scipy Radau": "black",
             "scipy BDF": "gray", "diffrax Kvaerno5": "#762a83", "diffrax Kvaerno3": "#c2a5cf",
             "diffrax Tsit5": "#e7298a"}.get(base)
    if m.endswith(ADAPTIVE):
        return dict(ls="--", marker="^", lw=2.0, ms=5, color=color)
    if m.startswith(PEERS):
        return dict(ls=":", marker="s", lw=1.4, ms=4, color=color)
    if m.startswith("eG"):
        return dict(ls="-", marker="o", lw=1.3, ms=4, color=color)
    return dict(ls="-", marker="o", lw=0.8, ms=2.5, color=color, alpha=0.6)


def plot(data, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(data["scenes"])
    fig, axes = plt.subplots(2, len(scenes), figsize=(7.5 * len(scenes), 11), squeeze=False)
    for col, key in enumerate(scenes):
        runs = data["scenes"][key]["runs"]
        for row, (ekey, ylabel) in enumerate((("error", "error (max of rel. positions, rel. H at T)"),
                                              ("error_D", "rel. error of the dissipated energy D(T)"))):
            ax = axes[row][col]
            for m in dict.fromkeys(r["method"] for r in runs):
                # in order of the setting (step or tolerance), not of the noisy wall time
                rs = sorted((r for r in runs if r["method"] == m and r.get(ekey) is not None
                             and np.isfinite(r[ekey]) and r[ekey] > 0),
                            key=lambda r: -r.get("h", r.get("rtol", 0.0)))
                if not rs:
                    continue
                ax.loglog([r["wall_s"] for r in rs], [r[ekey] for r in rs], label=m, **_style(m))
            if row == 0:
                for t in TARGETS:
                    ax.axhline(t, color="gray", lw=0.6, ls=":")
                lo, hi = ax.get_ylim()
                ax.set_ylim(lo, min(hi, 1.0))  # errors above 1 (unstable coarse steps) are off the chart
            d = data["scenes"][key]
            ax.set_title(f"{key} ({d['dofs']} unknowns in y), t in [0, {data['settings']['t_end']:g}]"
                         + ("" if row == 0 else ": jaxvisco only (the ODE peers do not integrate D)"), fontsize=9)
            ax.set_xlabel("wall time after compilation [s]")
            ax.set_ylabel(ylabel)
            ax.grid(True, which="both", lw=0.3)
            ax.legend(fontsize=7, ncol=2)
    fig.suptitle("Work-precision, lumped mass, 2-core CPU (shared: see the load averages in the JSON)\n"
                 "solid: constant step; dashed: eG(k), error-controlled steps (rtol = atol); dotted: peers\n"
                 "gray lines: the errors 1e-3, 1e-4, 1e-6 of the adaptive summary", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}", flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="refinement 1, t in [0, 1], few methods (< 3 min)")
    p.add_argument("--refinements", default=None)
    p.add_argument("--t-end", type=float, default=None)
    p.add_argument("--methods", default=None, help="comma list to restrict (e.g. eG(2),scipy Radau)")
    p.add_argument("--budget", type=float, default=None, help="seconds per run beyond which finer runs are skipped")
    p.add_argument("--out", default="work_precision")
    p.add_argument("--reference", choices=("eG", "radau"), default="eG",
                   help="radau: use the Radau rtol-1e-12 solution itself as the reference (no eG run)")
    p.add_argument("--merge", default=None,
                   help="comma list of results names to merge into --out (runs split over processes; a method "
                        "measured in a later file replaces its rows in earlier ones); no runs")
    p.add_argument("--rederive", default=None, metavar="NAMES",
                   help="comma list of results names whose summaries are recomputed from their runs (no runs)")
    p.add_argument("--replot", action="store_true", help="only redraw the PNG from the JSON")
    p.add_argument("--adaptive-only", action="store_true",
                   help="only the reference and the adaptive eG curves (no constant steps, no peers); merge the "
                        "result with a full run by --merge")
    p.add_argument("--check", choices=("radau", "eG-2h", "none"), default="radau",
                   help="cross-check of the eG reference: scipy Radau at rtol 1e-12 (default; ~12 min alone at "
                        "refinement 2), or eG(3) at twice the reference step")
    p.add_argument("--reuse-reference", default=None, metavar="NAME",
                   help="take each scene's reference (and its check) from results/NAME.json (same t_end) instead of "
                        "computing it: for runs split over processes")
    p.add_argument("--tols", default=None, help="comma list of rtol = atol for the adaptive eG and the peers "
                                                "(default 1e-2,...,1e-7)")
    p.add_argument("--hs", default=None, help="comma list of constant steps for every selected constant-step scheme "
                                              "(default: each scheme's own grid)")
    p.add_argument("--repeats", type=int, default=None, help="timed calls after the first (default 3)")
    p.add_argument("--diffrax-timeout", type=float, default=None,
                   help="wall-clock limit of one diffrax solver's subprocess (default 4 x budget)")
    p.add_argument("--diffrax-worker", default=None, help=argparse.SUPPRESS)
    p.add_argument("--ref", default=None, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.merge:
        merge(a.merge.split(","), a.out)
        return
    if a.rederive:
        for name in a.rederive.split(","):
            _derive(json.loads((RESULTS / f"{name}.json").read_text()), name)
        return
    if a.replot:
        plot(json.loads((RESULTS / f"{a.out}.json").read_text()), RESULTS / f"{a.out}.png")
        return
    if a.diffrax_worker:
        diffrax_worker(a.diffrax_worker, int(a.refinements), a.t_end, [float(t) for t in a.tols.split(",")],
                       a.budget, a.repeats, a.ref)
        return
    quick = a.quick
    T = a.t_end if a.t_end is not None else (1.0 if quick else 10.0)
    refinements = [int(r) for r in (a.refinements or ("1" if quick else "1,2")).split(",")]
    budget = a.budget if a.budget is not None else (8.0 if quick else 90.0)
    repeats = a.repeats if a.repeats is not None else (2 if quick else 3)
    # wall-clock limit of one diffrax solver's subprocess
    worker_timeout = a.diffrax_timeout if a.diffrax_timeout is not None else (70.0 if quick else 4 * budget)
    schemes = all_schemes()
    # Steps from coarse (errors near 1e-3, the loosest target of the adaptive summary) to fine.
    order2 = [0.4, 0.2, 0.1, 0.05, 0.025, 0.0125, 0.00625]
    order4 = [0.5, 0.2, 0.1, 0.05, 0.025, 0.0125]
    order6 = [1.0, 0.4, 0.2, 0.1, 0.05, 0.025]
    hs = {"cG(1)": order2, "eG(1)": order2, "Newmark": order2, "Midpoint": order2,
          "cG(2)": order4, "eG(2)": order4, "cG(3)": order6, "eG(3)": order6}
    tols = [1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7]
    adaptive = {k: schemes[k] for k in ("eG(1)", "eG(2)", "eG(3)")}
    adaptive_cap = 32768  # accepted steps at most (eG(1) at rtol 1e-7 took > 16 384 on r1 in session 30)
    peers = ["scipy Radau", "scipy BDF", "diffrax Kvaerno5", "diffrax Kvaerno3", "diffrax Tsit5"]
    ref_scheme, ref_h, ref_tol = "eG(3)", 0.005, 1e-12
    if quick:
        schemes = {k: schemes[k] for k in ("eG(1)", "eG(2)")}
        hs = {"eG(1)": [0.1, 0.05, 0.025], "eG(2)": [0.2, 0.1, 0.05, 0.025]}
        tols = [1e-3, 1e-5, 1e-7]
        adaptive = {k: adaptive[k] for k in ("eG(1)", "eG(2)")}
        adaptive_cap = 4096
        peers = ["scipy Radau", "scipy BDF", "diffrax Kvaerno5", "diffrax Tsit5"]
        ref_scheme, ref_h, ref_tol = "eG(2)", 0.0025, 1e-9
    if a.tols:
        tols = [float(t) for t in a.tols.split(",")]
    if a.hs:
        hs = {m: [float(h) for h in a.hs.split(",")] for m in hs}
    if a.methods:
        keep = set(a.methods.split(","))
        schemes = {k: v for k, v in schemes.items() if k in keep}
        adaptive = {k: v for k, v in adaptive.items() if k + ADAPTIVE in keep}
        peers = [m for m in peers if m in keep]
    if a.adaptive_only:
        schemes, peers = {}, []

    data = dict(machine=machine(), settings=dict(
        quick=quick, t_end=T, mass="lumped (HRZ) for every method, jaxvisco included",
        error="max(||x - x_ref|| / ||x_ref||, |H - H_ref| / |H_ref|) at t_end (both also reported)",
        jaxvisco_solver="NewtonKrylov() defaults (rtol 1e-10, GMRES with the condensed-tangent preconditioner)",
        peers="rtol = atol; scipy with jac=ode.jac (sparse CSC, exact); diffrax PIDController, default root "
              "finder (VeryChord, dense Jacobian by jacfwd, LU): diffrax/lineax have no sparse Jacobian path "
              "(a lineax GMRES root-finder solver failed to trace with diffrax 0.7.2 / lineax 0.1.1); diffrax "
              "runs in a subprocess stopped at a wall-clock limit; diffrax Tsit5 (explicit) added for reference",
        repeats=repeats, budget_s=budget, target_error=TARGET, tols=tols,
        adaptive=("eG(k) with stepsize_controller=PIDController(rtol=tol, atol=tol) (defaults otherwise: integral "
                  "controller, safety 0.9, factors in [0.2, 10], keep_band 1.2), first step tried T/100, "
                  f"max_steps={adaptive_cap}, frames only at 0 and T; the error estimate controls the interior "
                  "error of each step's time polynomial (order k+1), so errors at T lie well below rtol"),
        error_D=("|D(T) - D_ref(T)| / D_ref(T), D the cumulative dissipated energy of the scheme "
                 "(Solution.dissipated[-1]); null for the ODE peers, which do not integrate D (for the exact "
                 "solution D(T) = H(0) - H(T) here, no external work)"),
        adaptive_summary_targets=list(TARGETS), check=a.check, adaptive_only=a.adaptive_only), scenes={})
    for r in refinements:
        key = f"2D L-shape r{r}"
        scene = lshape(2, r, mass="lumped")
        ode = jv.semidiscrete(scene)
        print(f"{key}: {ode.n} unknowns (x {ode.n_x}, p {ode.n_x}, Gamma {ode.n_g})", flush=True)
        # Reference, and the Radau cross-check.
        cap_ref = int(round(T / ref_h))
        if ref_scheme in hs:
            cap_ref = max(cap_ref, max(int(round(T / h)) for h in hs[ref_scheme]))
        ref = None
        ref_wall = None
        reused = None
        if a.reuse_reference:
            src = json.loads((RESULTS / f"{a.reuse_reference}.json").read_text())
            if src["settings"]["t_end"] != T or "x_T" not in src["scenes"].get(key, {}).get("reference", {}):
                raise SystemExit(f"--reuse-reference {a.reuse_reference}: no reference of {key} at t_end = {T:g} "
                                 "with its positions (x_T) there")
            reused = dict(src["scenes"][key]["reference"])
            ref_scheme, ref_h = reused["scheme"], reused["h"]
            ref = dict(x=np.asarray(reused["x_T"]), H=reused["H"], D=reused.get("D"))
            print(f"  reference {ref_scheme} h={ref_h} from {a.reuse_reference}.json: H(T)={ref['H']:.12g}", flush=True)
        elif a.reference == "eG":
            t0 = time.perf_counter()
            sol = jv.simulate(scene, all_schemes()[ref_scheme], t1=T, dt0=ref_h, saveat=jv.SaveAt(every=cap_ref),
                              max_steps=cap_ref, root_finder=jv.NewtonKrylov(rtol=1e-12))
            ref_wall = time.perf_counter() - t0
            ref = dict(x=np.asarray(sol.x[-1]), H=float(sol.energy[-1]), D=float(sol.dissipated[-1]))
            print(f"  reference {ref_scheme} h={ref_h}: H(T)={ref['H']:.12g}, D(T)={ref['D']:.12g}, "
                  f"{ref_wall:.1f}s", flush=True)
        jax.block_until_ready(ode.rhs(0.0, ode.y0))
        ode.jac(0.0, ode.y0)
        if reused is not None:
            check = {k: v for k, v in reused.items() if k not in ("scheme", "h", "newton_rtol", "H", "D", "wall_s",
                                                                  "x_T")}
            check["reused_from"] = f"{a.reuse_reference}.json"
            ref_wall = reused.get("wall_s")
        elif a.check == "radau" or ref is None:
            t0 = time.perf_counter()
            rr = solve_ivp(ode.fun, (0.0, T), ode.y0, method="Radau", jac=ode.jac, rtol=ref_tol, atol=ref_tol)
            radau_wall = time.perf_counter() - t0
            yr = rr.y[:, -1]
            if ref is None:
                ref_scheme, ref_h = "scipy Radau", None
                ref = dict(x=np.asarray(ode.unpack(yr).x), H=float(ode.energy(yr)), D=None)
            check = dict(check="scipy Radau", radau_rtol=ref_tol, radau_success=bool(rr.success),
                         radau_steps=int(rr.t.size - 1), radau_wall_s=radau_wall,
                         diff_x=rel(ode.unpack(yr).x, ref["x"]),
                         diff_H=abs(float(ode.energy(yr)) - ref["H"]) / abs(ref["H"]), diff_D=None)
            print(f"  Radau rtol={ref_tol}: diff x {check['diff_x']:.2e}, H {check['diff_H']:.2e}, "
                  f"{rr.t.size - 1} steps, {radau_wall:.1f}s", flush=True)
        elif a.check == "eG-2h":
            t0 = time.perf_counter()
            s2 = jv.simulate(scene, all_schemes()[ref_scheme], t1=T, dt0=2 * ref_h, saveat=jv.SaveAt(every=cap_ref),
                             max_steps=cap_ref, root_finder=jv.NewtonKrylov(rtol=1e-12))
            w2 = time.perf_counter() - t0
            check = dict(check=f"{ref_scheme} at h = {2 * ref_h:g} (the difference bounds the error of that run; "
                               "the reference's own is ~2^-(2k) of it)", radau_rtol=None, check_wall_s=w2,
                         diff_x=rel(s2.x[-1], ref["x"]), diff_H=abs(float(s2.energy[-1]) - ref["H"]) / abs(ref["H"]),
                         diff_D=_error_D(s2.dissipated[-1], ref))
            print(f"  check {ref_scheme} h={2 * ref_h:g}: diff x {check['diff_x']:.2e}, H {check['diff_H']:.2e}, "
                  f"D {check['diff_D']:.2e}, {w2:.1f}s", flush=True)
        else:
            check = dict(check="none", radau_rtol=None, diff_x=None, diff_H=None, diff_D=None)
        runs = []

        def record(final=False):
            """Write the scene's runs so far (a run stopped from outside keeps what it measured)."""
            at, best, speedup = compare(runs)
            summ = adaptive_summary(runs)
            data["scenes"][key] = dict(
                refinement=r, dofs=ode.n, n_x=ode.n_x, n_gamma=ode.n_g,
                reference=dict(scheme=ref_scheme, h=ref_h, newton_rtol=1e-12, H=ref["H"], D=ref.get("D"),
                               wall_s=ref_wall, **check, x_T=np.asarray(ref["x"]).tolist()),
                runs=runs, wall_at_target_s=at, best_jaxvisco=best, speedup_at_target=speedup, adaptive_summary=summ,
                complete=final)
            data["adaptive_summary"] = {k: sc["adaptive_summary"] for k, sc in data["scenes"].items()}
            write_json(f"{a.out}.json", data)
            return at, best, speedup, summ

        for name, scheme in schemes.items():
            cap = max(int(round(T / h)) for h in hs[name])
            if name == ref_scheme:
                cap = max(cap, cap_ref)  # one compile serves the reference and these runs
            runs += run_jaxvisco(scene, name, scheme, hs[name], T, ref, cap, budget, repeats)
            record()
        for name, scheme in adaptive.items():
            runs += run_adaptive(scene, name, scheme, tols, T, ref, adaptive_cap, budget, repeats)
            record()
        for m in peers:
            lib, method = m.split()
            if lib == "scipy":
                runs += run_scipy(ode, method, tols, T, ref, budget, repeats)
            else:
                runs += run_diffrax(ode, method, tols, T, ref, budget, repeats, worker_timeout, r)
            record()
        at, best, speedup, summ = record(final=True)
        print(f"  wall at {TARGET:g}: " + ", ".join(f"{m} {w:.3g}s" if w else f"{m} n/a" for m, w in at.items()),
              flush=True)
        print(f"  best jaxvisco: {best}; speedups: {speedup}", flush=True)
        print_adaptive_summary(key, summ)
    plot(data, RESULTS / f"{a.out}.png")


if __name__ == "__main__":
    main()
