"""Adaptive against constant steps at equal error, and what a tolerance delivers (#62).

    python benchmarks/adaptive_work_precision.py [--refinements 1,3] [--rounds 5] [--quick]

#62's table: on the 2D L-shape with the lumped mass (as `work_precision.py`), refinement
1 to t = 10 and refinement 3 to t = 2, eG(1..3) with constant steps h and with
`PIDController(rtol=tol, atol=tol)` (defaults otherwise, first step a hundredth of the
run). Three error measures at t_end against eG(3) at a small constant step (Newton rtol
1e-12; its difference from twice that step is recorded): `error` = max(relative
position error |x - x_ref| / |x_ref|, relative energy error), the issue's measure;
`error_body` = max(root mean square position error over the body's size (the root mean
square distance from its centroid), energy error over the energy in the frame of the
centre of mass), what `PIDController`'s tolerance is of; and `error_D`, the relative
error of the dissipated energy D(t_end).

Wall times after compilation: every run is compiled (and its errors taken) first, then
timed in `--rounds` rounds, each round calling every run once in turn, so that a
change of the machine's load falls on all runs alike; the median of a run's rounds is
its wall time. The load averages before and after are recorded.

Summary, per refinement, error measure and target error: each curve's wall time at the
target (log-log interpolation along its work-precision front, `work_precision.front`),
the best constant-step eG and the best adaptive eG there, and their ratio
(adaptive / constant; #62's target: at most 1.3 for `error` at 1e-6 and 1e-4 on r1 and
1e-4 on r3). Where every run of a curve is more accurate than the target, its cheapest
run's time is an upper bound (`wall_at_most_s`, ratio marked as such). And per adaptive
run, the achieved error over tol (#62's target: within [0.1, 10] for tol 1e-3 ... 1e-7 on
r1, in `error_body`). Writes benchmarks/results/adaptive_work_precision.json.
"""

import argparse
import math
import os
import statistics
import time

from common import RESULTS, jv, lshape, machine, rel, write_json  # noqa: I001
from work_precision import at_most, front, interpolate_at  # noqa: I001

import numpy as np  # noqa: E402

SCHEMES = {"eG(1)": jv.eG(1), "eG(2)": jv.eG(2), "eG(3)": jv.eG(3)}
CASES = {  # refinement: t_end, reference step, constant steps per scheme, tolerances, targets
    1: dict(t_end=10.0, ref_h=0.005, targets=(1e-3, 1e-4, 1e-6),
            hs={"eG(1)": (0.25, 0.125, 0.0625, 0.03125, 0.015625, 0.0078125),
                "eG(2)": (0.5, 0.25, 0.125, 0.0625, 0.03125, 0.015625),
                "eG(3)": (1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125)},
            tols=(1e-3, 1e-4, 1e-5, 1e-6, 1e-7)),
    3: dict(t_end=2.0, ref_h=0.005, targets=(1e-3, 1e-4, 1e-5),
            hs={"eG(1)": (0.0625, 0.03125, 0.015625),
                "eG(2)": (0.25, 0.125, 0.0625, 0.03125),
                "eG(3)": (0.5, 0.25, 0.125, 0.0625)},
            tols=(1e-2, 1e-3, 1e-4, 1e-5)),
}
MEASURES = ("error", "error_body", "error_D")
CAP = 32768  # accepted steps at most (eG(1) at rtol 1e-7 on r1: ~7000)


def _rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


def errors(sol, ref):
    x = np.asarray(sol.x[-1])
    ex = rel(x, ref["x"])
    eH = abs(float(sol.energy[-1]) - ref["H"]) / abs(ref["H"])
    eD = abs(float(sol.dissipated[-1]) - ref["D"]) / abs(ref["D"])
    xb = _rms(x - ref["x"]) / _rms(ref["x"] - ref["x"].mean(axis=0))
    Hb = abs(float(sol.energy[-1]) - ref["H"]) / ref["H_body"]
    return dict(error=max(ex, eH), error_x=ex, error_H=eH, error_body=max(xb, Hb), error_x_body=xb,
                error_H_body=Hb, error_D=eD)


def reference(scene, T, h):
    tight = jv.NewtonKrylov(rtol=1e-12)
    n = int(round(T / h))
    out = []
    for step in (h, 2 * h):
        sol = jv.simulate(scene, jv.eG(3), t1=T, dt0=step, saveat=jv.SaveAt(every=n), max_steps=n, solver=tight)
        P = np.asarray(sol.p[-1]).sum(axis=0)
        H = float(sol.energy[-1])
        out.append(dict(x=np.asarray(sol.x[-1]), H=H, D=float(sol.dissipated[-1]),
                        H_body=H - float(P @ P) / (2.0 * float(scene.mass()))))
    ref, check = out
    return ref, dict(scheme="eG(3)", h=h, newton_rtol=1e-12, H=ref["H"], H_body=ref["H_body"], D=ref["D"],
                     check=f"eG(3) at h = {2 * h:g}", **{f"diff_{k}": v for k, v in errors_of(check, ref).items()})


def errors_of(a, ref):
    return dict(x=rel(a["x"], ref["x"]), H=abs(a["H"] - ref["H"]) / abs(ref["H"]), D=abs(a["D"] - ref["D"]) / ref["D"])


def runs_of(scene, case, quick):
    """(label, family, scheme name, setting, call) for every run of a refinement."""
    T = case["t_end"]
    out = []
    for name, scheme in SCHEMES.items():
        hs = case["hs"][name][:3] if quick else case["hs"][name]
        cap = max(int(round(T / h)) for h in hs)
        for h in hs:
            out.append((f"{name} h={h:g}", "constant", name, h,
                        lambda scheme=scheme, h=h, cap=cap: jv.simulate(
                            scene, scheme, t1=T, dt0=h, saveat=jv.SaveAt(every=cap), max_steps=cap, throw=False)))
    for name, scheme in SCHEMES.items():
        for tol in (case["tols"][1:4] if quick else case["tols"]):
            ctrl = jv.PIDController(tol, tol)
            out.append((f"{name} adaptive tol={tol:g}", "adaptive", name, tol,
                        lambda scheme=scheme, ctrl=ctrl: jv.simulate(
                            scene, scheme, 0.0, T, None, stepsize_controller=ctrl, saveat=jv.SaveAt(every=CAP),
                            max_steps=CAP, throw=False)))
    return out


def measure(scene, case, ref, rounds, quick, budget_s):
    rows, calls = [], []
    for label, family, name, setting, call in runs_of(scene, case, quick):
        t0 = time.perf_counter()
        sol = call()
        first = time.perf_counter() - t0
        row = dict(label=label, family=family, scheme=name, status=sol.status, steps=int(sol.n_steps),
                   rejections=int(np.sum(np.asarray(sol.rejections))),
                   newton_iterations=int(np.sum(np.asarray(sol.newton_iterations))),
                   chord_iterations=int(np.sum(np.asarray(sol.chord_iterations))), first_call_s=first)
        row.update(h=setting) if family == "constant" else row.update(tol=setting)
        if sol.status == "done":
            row.update(errors(sol, ref))
            if family == "adaptive":
                for m in MEASURES:
                    row[f"{m}_over_tol"] = row[m] / setting
                hs = np.asarray(sol.step_h)
                row.update(h_min=float(hs.min()), h_median=float(np.median(hs)), h_max=float(hs.max()))
        print(f"  {label:28s} {sol.status:6s} steps {row['steps']:6d} rej {row['rejections']:3d} "
              f"newton {row['newton_iterations']:4d} chord {row['chord_iterations']:6d} "
              f"error {row.get('error', math.nan):.2e} body {row.get('error_body', math.nan):.2e} D {row.get('error_D', math.nan):.2e} first {first:.2f}s",
              flush=True)
        rows.append(row)
        calls.append(call if sol.status == "done" else None)
    times = [[] for _ in rows]
    t_start = time.perf_counter()
    for r in range(rounds):
        for i, call in enumerate(calls):
            if call is None:
                continue
            t0 = time.perf_counter()
            call()
            times[i].append(time.perf_counter() - t0)
        print(f"  round {r + 1}/{rounds} done, load {os.getloadavg()[0]:.2f}", flush=True)
        if time.perf_counter() - t_start > budget_s and r >= 2:
            print(f"  over the budget of {budget_s:.0f} s: {r + 1} rounds", flush=True)
            break
    for row, ts in zip(rows, times):
        row["times_s"] = ts
        row["wall_s"] = statistics.median(ts) if ts else math.nan
    return rows


def summary(rows, targets):
    """Per measure and target: each curve's wall time there, the best constant-step and
    the best adaptive eG, and the ratio adaptive / constant."""
    out = {}
    curves = {}
    for r in rows:
        curves.setdefault((r["family"], r["scheme"]), []).append(r)
    for m in MEASURES:
        out[m] = {}
        for target in targets:
            at, bound = {}, {}
            for (family, name), rs in curves.items():
                pts = [dict(wall_s=r["wall_s"], error=r[m]) for r in rs if m in r and np.isfinite(r["wall_s"])]
                w = interpolate_at(pts, target)
                key = f"{name} {family}"
                if w is not None:
                    at[key] = w
                elif at_most(pts, target) is not None:
                    bound[key] = at_most(pts, target)
            best = {}
            for family in ("constant", "adaptive"):
                cands = {k: (w, False) for k, w in at.items() if k.endswith(family)}
                cands.update({k: (w, True) for k, w in bound.items() if k.endswith(family) and
                              (k not in cands)})
                if cands:
                    k = min(cands, key=lambda k: cands[k][0])
                    best[family] = dict(curve=k, wall_s=cands[k][0], upper_bound=cands[k][1])
            ratio = None
            if "constant" in best and "adaptive" in best:
                ratio = best["adaptive"]["wall_s"] / best["constant"]["wall_s"]
            out[m][f"{target:g}"] = dict(wall_at_error_s=at, wall_at_most_s=bound, best=best,
                                         ratio_adaptive_over_constant=ratio,
                                         ratio_is_bound=bool(best.get("adaptive", {}).get("upper_bound")
                                                             or best.get("constant", {}).get("upper_bound")))
    return out


def print_summary(key, summ):
    for m, by_target in summ.items():
        for t, d in by_target.items():
            b = d["best"]
            parts = [f"{f} {b[f]['curve']} {b[f]['wall_s']:.3f}s" + (" (at most)" if b[f]["upper_bound"] else "")
                     for f in ("constant", "adaptive") if f in b]
            r = d["ratio_adaptive_over_constant"]
            print(f"{key} {m} at {t}: " + ", ".join(parts) + (f"; adaptive / constant {r:.2f}" if r else ""),
                  flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--refinements", default="1,3")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--budget", type=float, default=900.0, help="seconds of timed rounds per refinement (at least 3)")
    ap.add_argument("--quick", action="store_true", help="refinement 1, three settings per curve, 3 rounds")
    ap.add_argument("--out", default="adaptive_work_precision")
    a = ap.parse_args()
    refinements = [1] if a.quick else [int(r) for r in a.refinements.split(",")]
    rounds = 3 if a.quick else a.rounds
    data = dict(machine=machine(), settings=dict(
        mass="lumped (HRZ)", solver="NewtonKrylov() defaults", controller="PIDController(rtol=tol, atol=tol)",
        error="max(|x - x_ref| / |x_ref|, |H - H_ref| / |H_ref|) at t_end",
        error_body="max(rms(x - x_ref) / rms(x_ref - centroid), |H - H_ref| / (H_ref - |P|^2 / 2m)) at t_end",
        error_D="|D - D_ref| / D_ref at t_end",
        timing=f"median of {rounds} rounds; each round calls every run once in turn, after a compiling call",
        quick=a.quick), scenes={})
    for r in refinements:
        case = CASES[r]
        key = f"2D L-shape r{r}"
        scene = lshape(2, r, mass="lumped")
        print(f"{key}, t_end = {case['t_end']:g}", flush=True)
        ref, ref_info = reference(scene, case["t_end"], case["ref_h"])
        print(f"  reference eG(3) h = {case['ref_h']:g}; at twice the step: x {ref_info['diff_x']:.1e}, "
              f"H {ref_info['diff_H']:.1e}, D {ref_info['diff_D']:.1e}", flush=True)
        load0 = list(os.getloadavg())
        rows = measure(scene, case, ref, rounds, a.quick, a.budget)
        summ = summary(rows, case["targets"])
        print_summary(key, summ)
        data["scenes"][key] = dict(refinement=r, t_end=case["t_end"], reference=ref_info, runs=rows, summary=summ,
                                   load_average_before=load0, load_average_after=list(os.getloadavg()))
        write_json(f"{a.out}.json", data)


if __name__ == "__main__":
    main()
