"""``jaxvisco paper``: the L-shape comparison of Groß & Betsch (2005), cG(1) against
eG(1) with a step-size change at t = 20 and with large steps from the outset, one results
file per run and the energy figure ``energy.png``; `PAPER_T` and `QUICK_T` are its final
times.
"""

import concurrent.futures
import os
import sys
import threading

import numpy as np

from ._checks import _warn_energy
from ._chunked import chunk_size, run_chunked, run_into

PAPER_T = 60.0
QUICK_T = 24.0
# The two integrators' runs in two threads (False: one after the other). Each thread
# compiles its own time loop (XLA compiles without the GIL) and then runs it, so on two
# cores the compiles and runs overlap. `jaxvisco paper --quick` with no compilation cache,
# whole process, 2-core VM with other tenants (load 0.7-1.6), five alternating rounds:
# one after the other 23.4-30.1 s (median 28.6), in threads 22.2-27.3 s (median 25.8).
PARALLEL = True


def _paper(args):
    import matplotlib

    matplotlib.use("Agg")

    import jaxvisco as jv

    out = args.out
    if args.quick:
        T = QUICK_T if args.t_end is None else args.t_end
    else:
        T = PAPER_T if args.t_end is None else args.t_end
    # h = 0.2 is already too large for cG(1) before t = 20 (its energy grows ~9x by
    # t = 19); h = 0.1 keeps it bounded there, and running it costs little beside
    # compilation, so --quick only shortens the final time.
    schedule = [(20.0, 0.1), (T, 1.0)] if T > 20.0 else [(T, 0.1)]
    scene = jv.scenes.lshape(dim=2, refinement=1)
    runs = [("schedule", jv.StepTo.from_schedule(0.0, T, schedule)), ("large", jv.StepTo.from_schedule(0.0, T, 1.0))]
    c = chunk_size([len(steps) for _, steps in runs], target=50)
    integrators = (("cG1", jv.cG(1)), ("eG1", jv.eG(1)))
    paths = {f"{a}_{b}": os.path.join(out, f"{a}_{b}.h5") for a, _ in integrators for b, _ in runs}
    existing = [p for p in paths.values() if os.path.exists(p)]
    if existing and not args.overwrite:
        raise FileExistsError(f"results file {existing[0]!r} exists; pass --overwrite to replace the results in "
                              f"{out!r}, or choose another --out.")
    os.makedirs(out, exist_ok=True)
    stop = threading.Event()

    def run_integrator(scheme_name, integrator):
        done = []
        for sched_name, steps in runs:
            label = f"{scheme_name}_{sched_name}"
            path = paths[label]
            attrs = dict(scene="lshape", refinement=1, integrator=integrator.describe(),
                         parameters=dict(schedule=schedule if sched_name == "schedule" else [(T, 1.0)], t_end=T))
            w = jv.ResultsWriter(path, scene, attrs, overwrite=args.overwrite)
            r = run_into(w, lambda: run_chunked(scene, integrator, steps, chunk=c, writer=w, label=label,
                                                quiet=args.quiet, should_stop=stop.is_set))
            saved = jv.read_results(path)
            r.update(t=saved["t"], energy=saved["energy"])
            done.append((scheme_name, sched_name, r))
            sched_txt = "h=0.1->1.0@t=20" if sched_name == "schedule" else "h=1.0"
            print(f"{scheme_name:4s} {sched_txt:16s} status={r['status']:11s} H0={r['energy'][0]:.6g} "
                  f"H_end={r['energy'][-1]:.6g} (t={r['t_last']:.4g}) steps={r['steps']} wall={r['wall']:.1f}s",
                  flush=True)
            _warn_energy(saved, label)
            if stop.is_set():
                break
        return done

    # One thread per integrator (`PARALLEL`); the figure keeps the order of `integrators`.
    results = []
    with concurrent.futures.ThreadPoolExecutor(max_workers=len(integrators) if PARALLEL else 1,
                                               thread_name_prefix="jaxvisco-paper") as pool:
        futures = [pool.submit(run_integrator, *it) for it in integrators]
        try:
            for f in futures:
                results += f.result()
        except BaseException:  # Ctrl-C or a failed run: the other thread stops after its chunk
            stop.set()
            raise
    _paper_figure(results, os.path.join(out, "energy.png"))
    if not args.quiet:
        print(f"wrote {out}/energy.png and {len(results)} results files", file=sys.stderr)
    return 0


def _paper_figure(results, path):
    """The energy figure of the `_paper` runs (`results`: (scheme, schedule, run dict)
    triples), H of all four runs and a zoom on eG(1), written to `path`."""
    import matplotlib.pyplot as plt

    fig, (ax, az) = plt.subplots(1, 2, figsize=(12, 5))
    styles = {"cG1": "tab:red", "eG1": "tab:blue"}
    for scheme_name, sched_name, r in results:
        ls = "-" if sched_name == "schedule" else "--"
        for a in (ax, az) if scheme_name == "eG1" else (ax,):
            a.plot(r["t"], r["energy"], ls, color=styles[scheme_name], label=f"{scheme_name} {sched_name}")
        if r["status"] == "failed":
            ax.plot(r["t"][-1], r["energy"][-1], "x", color=styles[scheme_name], ms=10, mew=2)
            ax.annotate("diverged", (r["t"][-1], r["energy"][-1]), textcoords="offset points", xytext=(5, 5),
                        color=styles[scheme_name])
    H0 = results[0][2]["energy"][0]
    eg = np.concatenate([r["energy"] for s_, _, r in results if s_ == "eG1"])
    az.set_ylim(eg.min() - 0.1 * (H0 - eg.min()) - 1e-3, H0 + 0.3 * (H0 - eg.min()) + 1e-3)
    az.set_title("zoom on eG(1): energy never increases")
    for a in (ax, az):
        a.axvline(20.0, color="gray", lw=0.8, ls=":")
        a.text(20.0, 0.98, " step change", transform=a.get_xaxis_transform(), va="top", color="gray")
        a.set_xlabel("t")
        a.set_ylabel("total energy H")
    ax.set_yscale("log")
    ax.set_title("L-shape, refinement 1: cG(1) vs eG(1)")
    ax.legend()
    az.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
