"""Error-controlled steps on the paper's scene: the step size over time, and what it buys.

    python benchmarks/adaptive_steps.py [--quick] [--t-end 60]

The paper's 2D L-shape (`jaxvisco.scenes.lshape(2, 1)`: consistent mass, both branches
Neo-Hooke) to t = 60 with eG(1), eG(2), eG(3) and `PIDController(rtol=tol, atol=tol)`,
tol = 1e-3 and 1e-4 (first step tried: a hundredth of the run; every accepted step saved,
`save_every=1`: the 2D mesh of refinement 1 is small). Per run: accepted steps,
rejections, Newton-Krylov and chord iterations (all attempts, rejected ones included),
wall time after compilation (median of repeats) and with the compile time of the scheme's
program added (one program serves both tolerances), min/median/max h, and the energy
balance residual max_n |(H + D - W)_{n+1} - (H + D - W)_n| / |H_0| over the step frames.

Each adaptive run is then compared with the constant step h = T/N of the same number N
of steps (same scheme): final-time position error ||x(T) - x_ref(T)|| / ||x_ref(T)||
of both against a tight reference, adaptive eG(3) at rtol = atol = 1e-8 (its difference
from adaptive eG(3) at 1e-7 is reported as a check). Informative, not a test.

Writes benchmarks/results/adaptive_steps.json and adaptive_steps.png.
"""

import argparse
import time

from common import RESULTS, jv, machine, rel, timed, write_json  # noqa: I001

import numpy as np  # noqa: E402

TOLS = (1e-3, 1e-4)
KS = (1, 2, 3)


def balance_residual(sol):
    """max_n |(H + D - W)_{n+1} - (H + D - W)_n| / |H_0| over the saved frames."""
    r = np.asarray(sol.energy) + np.asarray(sol.dissipated) - np.asarray(sol.external_work)
    return float(np.max(np.abs(np.diff(r))) / abs(float(sol.energy[0]))) if r.size > 1 else 0.0


def adaptive_run(scene, k, tol, T, cap, repeats):
    ctrl = jv.PIDController(rtol=tol, atol=tol)

    def go():
        return jv.simulate(scene, jv.eG(k), 0.0, T, None, stepsize_controller=ctrl, saveat=jv.SaveAt(every=1),
                           max_steps=cap, throw=False)

    sol, first, wall, times = timed(go, repeats=repeats)
    return sol, first, wall, times


def constant_run(scene, k, n, T, cap, repeats):
    def go():
        return jv.simulate(scene, jv.eG(k), 0.0, T, T / n, saveat=jv.SaveAt(every=cap), max_steps=cap, throw=False)

    return timed(go, repeats=repeats)


def plot(data, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {1: "#d6604d", 2: "#2166ac", 3: "#1b7837"}
    styles = {1e-3: "-", 1e-4: "--"}
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 9), sharex=True)
    for r in data["runs"]:
        t_end, h = np.asarray(r["series"]["step_t"]), np.asarray(r["series"]["step_h"])
        t_start = t_end - h
        ts = np.ravel(np.column_stack([t_start, t_end]))
        ax1.semilogy(ts, np.repeat(h, 2), styles.get(r["rtol"], "-"), color=colors[r["k"]], lw=1.2,
                     label=f"{r['scheme']} rtol=atol={r['rtol']:g}: {r['steps']} steps, {r['rejections']} rejected")
        rej = np.asarray(r["series"]["rejections"]) > 0
        if rej.any():
            ax1.plot(t_start[rej], h[rej], "x", color=colors[r["k"]], ms=5)
    ax1.set_ylabel("accepted step h")
    ax1.grid(True, which="both", lw=0.3)
    ax1.legend(fontsize=7)
    ax1.set_title(f"{data['settings']['scene']}, adaptive eG(k) (x: a step accepted after rejections)", fontsize=9)
    ax2b = ax2.twinx()
    for r in data["runs"]:
        s = r["series"]
        ls = styles.get(r["rtol"], "-")
        ax2.plot(s["t"], s["energy"], ls, color=colors[r["k"]], lw=1.0, label=f"H, {r['scheme']} {r['rtol']:g}")
        ax2b.plot(s["t"], s["dissipated"], ls, color=colors[r["k"]], lw=1.0, alpha=0.6)
    ax2.set_xlabel("t")
    ax2.set_ylabel("energy H(t) (left, thin lines from the top)")
    ax2b.set_ylabel("dissipated energy D(t) (right, from 0)")
    ax2.grid(True, lw=0.3)
    ax2.legend(fontsize=7, loc="center right")
    ax2.set_title("H(t) and D(t) at every accepted step (H + D = H(0): no external work)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}", flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="t in [0, 5], eG(1) and eG(2) at 1e-3 only")
    p.add_argument("--t-end", type=float, default=None)
    p.add_argument("--repeats", type=int, default=None, help="timed calls after the first (default 2)")
    p.add_argument("--replot", action="store_true", help="only redraw the PNG from the JSON")
    a = p.parse_args(argv)
    if a.replot:
        import json

        plot(json.loads((RESULTS / "adaptive_steps.json").read_text()), RESULTS / "adaptive_steps.png")
        return
    T = a.t_end if a.t_end is not None else (5.0 if a.quick else 60.0)
    ks, tols = ((1, 2), (1e-3,)) if a.quick else (KS, TOLS)
    repeats = a.repeats if a.repeats is not None else (1 if a.quick else 2)
    cap = 8192  # accepted steps at most (one compiled program per scheme for every run of it)
    ref_tol, check_tol, ref_cap = 1e-8, 1e-7, 32768
    scene = jv.scenes.lshape(2, 1)
    data = dict(machine=machine(), settings=dict(
        scene="jaxvisco.scenes.lshape(2, 1) (paper data, consistent mass)", t_end=T, tols=list(tols),
        schemes=[f"eG({k})" for k in ks], max_steps=cap, save_every=1, repeats=repeats,
        controller="PIDController(rtol=tol, atol=tol), defaults otherwise; first step tried T/100",
        solver="NewtonKrylov() defaults",
        iterations="newton = Newton-Krylov iterations, chord = chord iterations on the stored factorization, "
                   "both summed over all attempts (rejected ones included)",
        wall="wall_s: median of the timed calls after the first; compile_s: the scheme's first call minus a "
             "timed call, measured on its first tolerance (the program serves both); wall_incl_compile_s = "
             "wall_s + compile_s",
        balance="max over consecutive step frames of |(H + D - W)_{n+1} - (H + D - W)_n| / |H_0|",
        constant_step="same scheme at h = T / N, N the adaptive run's accepted steps",
        reference=f"adaptive eG(3) at rtol = atol = {ref_tol:g} (max_steps {ref_cap}); check: adaptive eG(3) at "
                  f"{check_tol:g}"), runs=[])

    # The reference first (its program is eG(3)'s with another capacity).
    t0 = time.perf_counter()
    ref = jv.simulate(scene, jv.eG(3), 0.0, T, None, stepsize_controller=jv.PIDController(rtol=ref_tol, atol=ref_tol),
                      saveat=jv.SaveAt(every=ref_cap), max_steps=ref_cap, throw=False)
    ref_wall = time.perf_counter() - t0
    x_ref = np.asarray(ref.x[-1])
    chk = jv.simulate(scene, jv.eG(3), 0.0, T, None,
                      stepsize_controller=jv.PIDController(rtol=check_tol, atol=check_tol),
                      saveat=jv.SaveAt(every=ref_cap), max_steps=ref_cap, throw=False)
    data["reference"] = dict(scheme="eG(3) adaptive", rtol=ref_tol, status=ref.status, steps=int(ref.n_steps),
                             rejections=int(np.sum(np.asarray(ref.rejections))), wall_incl_compile_s=ref_wall,
                             H_end=float(ref.energy[-1]), D_end=float(ref.dissipated[-1]),
                             check=dict(rtol=check_tol, status=chk.status, steps=int(chk.n_steps),
                                        diff_x=rel(chk.x[-1], x_ref)))
    print(f"reference eG(3) rtol {ref_tol:g}: {ref.status}, {int(ref.n_steps)} steps, {ref_wall:.1f}s; "
          f"eG(3) at {check_tol:g} ({int(chk.n_steps)} steps) differs by {rel(chk.x[-1], x_ref):.2e}", flush=True)

    for k in ks:
        compile_s = None
        for tol in tols:
            sol, first, wall, times = adaptive_run(scene, k, tol, T, cap, repeats)
            if compile_s is None:
                compile_s = first - wall
            n = int(sol.n_steps)
            hs = np.asarray(sol.step_h)
            newton = int(np.sum(np.asarray(sol.newton_iterations)))
            chord = int(np.sum(np.asarray(sol.chord_iterations)))
            ok = sol.status == "done"
            err = rel(sol.x[-1], x_ref) if ok else None
            run = dict(scheme=f"eG({k})", k=k, rtol=tol, atol=tol, status=sol.status, steps=n,
                       rejections=int(np.sum(np.asarray(sol.rejections))), newton_iterations=newton,
                       chord_iterations=chord, newton_plus_chord=newton + chord,
                       krylov_iterations=int(np.sum(np.asarray(sol.krylov_iterations))),
                       wall_s=wall, times_s=times, first_call_s=first, compile_s=compile_s,
                       wall_incl_compile_s=wall + compile_s,
                       h_min=float(hs.min()), h_median=float(np.median(hs)), h_max=float(hs.max()),
                       balance_residual=balance_residual(sol), H_end=float(sol.energy[-1]),
                       D_end=float(sol.dissipated[-1]), error_x=err)
            print(f"eG({k}) tol {tol:g}: {sol.status}, {n} steps, {run['rejections']} rejected, newton {newton} "
                  f"+ chord {chord}, wall {wall:.2f}s (first call {first:.1f}s), h {run['h_min']:.3g} / "
                  f"{run['h_median']:.3g} / {run['h_max']:.3g}, balance {run['balance_residual']:.2e}, "
                  f"error x {err if err is not None else float('nan'):.2e}", flush=True)
            if ok:
                csol, cfirst, cwall, ctimes = constant_run(scene, k, n, T, cap, repeats)
                cerr = rel(csol.x[-1], x_ref) if csol.status == "done" else None
                run["constant_step"] = dict(h=T / n, steps=n, status=csol.status, error_x=cerr, wall_s=cwall,
                                            times_s=ctimes, first_call_s=cfirst,
                                            newton_iterations=int(np.sum(np.asarray(csol.newton_iterations))),
                                            chord_iterations=int(np.sum(np.asarray(csol.chord_iterations))))
                run["error_ratio_constant_over_adaptive"] = (cerr / err if (cerr is not None and err) else None)
                print(f"   constant h = {T / n:.4g} ({n} steps): {csol.status}, error x "
                      f"{cerr if cerr is not None else float('nan'):.2e} (adaptive {err:.2e}), wall {cwall:.2f}s",
                      flush=True)
            step_t = np.asarray(sol.step_t)
            run["series"] = dict(step_t=step_t.tolist(), step_h=hs.tolist(),
                                 rejections=np.asarray(sol.rejections).tolist(), t=np.asarray(sol.t).tolist(),
                                 energy=np.asarray(sol.energy).tolist(), dissipated=np.asarray(sol.dissipated).tolist())
            data["runs"].append(run)
            write_json("adaptive_steps.json", data)
    write_json("adaptive_steps.json", data)
    plot(data, RESULTS / "adaptive_steps.png")


if __name__ == "__main__":
    main()
