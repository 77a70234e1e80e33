"""Stability stress test: step sizes × schemes × material variants on the 2D L-shape.

    python benchmarks/stability.py [--quick]

h ∈ {0.05, 0.1, 0.25, 0.5, 1, 2, 4} × {cG(1), cG(2), eG(1), eG(2), Newmark, Midpoint} on the
paper's 2D L-shape (refinement 1, consistent mass) up to t = 100, for three materials:
the paper's, a stiff one (η_dev, η_vol / 1000) and a nearly incompressible one
(λ = 1000 μ in both branches). Per run: diverged or not, largest one-step energy increase,
final energy, whether equilibrium was reached (kinetic energy relative to the rigid-body
motion and the step's dissipation below 1e-8 H_0: the run stops there), Newton failures
(halved steps). All runs of one scheme share one compiled program (same step capacity,
material parameters are array leaves). Writes benchmarks/results/stability.json, .md, .png.
"""

import argparse
import time

from common import RESULTS, jv, machine, write_json  # noqa: I001

import numpy as np  # noqa: E402

from jaxvisco._integrate._frames import relative_kinetic_energy  # noqa: E402
from jaxvisco.scenes._lshape import PAPER  # noqa: E402

EQ_TOL = 1e-8
INCREASE_TOL = 1e-9  # one-step energy increase (relative to H0) that still counts as rounding


def variants():
    return {
        "paper": jv.scenes.lshape(2, 1),
        "stiff (eta/1000)": jv.scenes.lshape(2, 1, eta_dev=PAPER["eta_dev"] / 1000, eta_vol=PAPER["eta_vol"] / 1000),
        "incompressible (lam=1000 mu)": jv.scenes.lshape(2, 1, lam=1000 * PAPER["mu"]),
    }


def schemes():
    return {"eG(1)": jv.eG(1), "eG(2)": jv.eG(2), "cG(1)": jv.cG(1), "cG(2)": jv.cG(2), "Newmark": jv.Newmark(),
            "Midpoint": jv.Midpoint()}


def one_run(scene, scheme, h, T, cap, max_halvings=6):
    t0 = time.perf_counter()
    sol = jv.simulate(scene, scheme, t1=T, dt0=h, max_steps=cap, throw=False, event=jv.Equilibrium(EQ_TOL),
                      max_halvings=max_halvings)
    wall = time.perf_counter() - t0
    H = np.asarray(sol.energy)
    H0 = float(H[0])
    finite = np.all(np.isfinite(H))
    dH = np.diff(H) / abs(H0) if H.size > 1 else np.zeros(1)
    max_inc = float(np.nanmax(dH)) if dH.size else 0.0
    st = sol.state(-1)
    rke = float(relative_kinetic_energy(scene, st.x, st.p)) / abs(H0)
    diverged = sol.status == "failed" or not finite or float(np.nanmax(np.abs(H))) > 10 * abs(H0)
    return dict(
        h=h, status=sol.status, diverged=bool(diverged), t_final=float(sol.t[-1]), steps=int(sol.n_steps),
        H0=H0, H_final=float(H[-1]), max_step_increase_rel=max_inc,
        energy_nonincreasing=bool(not diverged and max_inc <= INCREASE_TOL),
        equilibrium=bool(sol.status == "equilibrium" or (not diverged and rke < EQ_TOL)),
        relative_kinetic_final=rke, newton_failures=int(np.sum(np.asarray(sol.rejections))),
        newton_per_step=float(np.mean(np.asarray(sol.newton_iterations))) if sol.n_steps else None, wall_s=wall)


def table(rows, variant_names, scheme_names, hs):
    out = []
    for v in variant_names:
        out.append(f"\n### {v}\n")
        out.append("Cell: `S` stable with non-increasing energy, `s` stable but energy rose in some step "
                   "(largest rise / H0 given), `D` diverged (energy blow-up or non-finite, or a failed solve after "
                   "energy rose), `F` Newton failed even after the allowed halvings with no energy rise so far "
                   "(the run stops there); `*` equilibrium reached; (n) Newton failures (halved steps); t= the "
                   "time reached by a run that stopped.\n")
        out.append("| scheme | " + " | ".join(f"h={h:g}" for h in hs) + " |")
        out.append("|---" * (len(hs) + 1) + "|")
        for s in scheme_names:
            cells = []
            for h in hs:
                r = next((r for r in rows if r["variant"] == v and r["scheme"] == s and r["h"] == h), None)
                if r is None:
                    cells.append("–")
                    continue
                newton_only = (r["status"] == "failed" and np.isfinite(r["max_step_increase_rel"])
                               and r["max_step_increase_rel"] <= INCREASE_TOL and abs(r["H_final"]) <= 10 * abs(r["H0"]))
                if newton_only:
                    c = "F"
                elif r["diverged"]:
                    c = "D"
                else:
                    c = "S" if r["energy_nonincreasing"] else f"s {r['max_step_increase_rel']:.1e}"
                if r["equilibrium"]:
                    c += "*"
                if r["newton_failures"]:
                    c += f" ({r['newton_failures']})"
                if r["status"] == "failed":
                    c += f" t={r['t_final']:.3g}"
                cells.append(c)
            out.append(f"| {s} | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def plot(rows, variant_names, scheme_names, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(variant_names), figsize=(6 * len(variant_names), 4.8), squeeze=False)
    for ax, v in zip(axes[0], variant_names):
        for i, s in enumerate(scheme_names):
            rs = sorted((r for r in rows if r["variant"] == v and r["scheme"] == s), key=lambda r: r["h"])
            if not rs:
                continue
            h = [r["h"] for r in rs]
            inc = [max(r["max_step_increase_rel"], 1e-17) if np.isfinite(r["max_step_increase_rel"]) else 1e3
                   for r in rs]
            line, = ax.loglog(h, inc, "o-", label=s, ms=4, lw=1)
            for r, y in zip(rs, inc):
                if r["diverged"]:
                    ax.plot(r["h"], y, "x", color=line.get_color(), ms=10, mew=2)
        ax.axhline(INCREASE_TOL, color="gray", ls=":", lw=0.8)
        ax.set_title(v, fontsize=9)
        ax.set_xlabel("h")
        ax.set_ylabel("largest one-step energy increase / H0 (x: diverged)")
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("Stability on the 2D L-shape to t = 100 (below the dotted line: rounding)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}", flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="h in {0.25, 1, 4}, t in [0, 20], paper and stiff")
    p.add_argument("--t-end", type=float, default=None)
    p.add_argument("--schemes", default=None)
    p.add_argument("--hs", default=None, help="comma list of step sizes (default: the issue's seven)")
    p.add_argument("--max-halvings", type=int, default=6, help="simulate's max_halvings (a run fails beyond it)")
    p.add_argument("--out", default="stability")
    p.add_argument("--note", default=None, help="with --from-json: a note added to the results")
    p.add_argument("--inputs", default=None, help="with --from-json: comma list of results files (names) to merge")
    p.add_argument("--from-json", action="store_true",
                   help="rebuild the table, summary and plot from an existing (possibly partial) results file")
    a = p.parse_args(argv)
    if a.from_json:
        import json

        names = a.inputs.split(",") if a.inputs else [a.out]
        data = json.loads((RESULTS / f"{names[0]}.json").read_text())
        for other in names[1:]:  # runs of the same settings split over processes
            more = json.loads((RESULTS / f"{other}.json").read_text())
            data["rows"] += more["rows"]
            data.setdefault("merged_from", names)
            data.setdefault("machine_of_merged", []).append(more["machine"])
        if a.note:
            data["note"] = a.note
        finish(data, data["rows"], list(dict.fromkeys(r["variant"] for r in data["rows"])),
               list(dict.fromkeys(r["scheme"] for r in data["rows"])), data["settings"]["hs"],
               data["settings"]["t_end"], a.out)
        return
    T = a.t_end if a.t_end is not None else (20.0 if a.quick else 100.0)
    hs = [0.25, 1.0, 4.0] if a.quick else [0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 4.0]
    if a.hs:
        hs = sorted(float(h) for h in a.hs.split(","))
    vs = variants()
    sc = schemes()
    if a.quick:
        sc = {k: sc[k] for k in ("cG(1)", "eG(1)")}
        vs = {k: vs[k] for k in ("paper", "stiff (eta/1000)")}
    if a.schemes:
        sc = {k: v for k, v in sc.items() if k in a.schemes.split(",")}
    cap = int(round(T / min(hs)))
    rows = []
    data = dict(machine=machine(), settings=dict(
        t_end=T, hs=hs, quick=a.quick, scene="2D L-shape refinement 1, consistent mass (jaxvisco.scenes.lshape)",
        equilibrium_tolerance=EQ_TOL, increase_tolerance=INCREASE_TOL, step_capacity=cap,
        solver=f"NewtonKrylov() defaults; failed steps halved up to {a.max_halvings} times",
        max_halvings=a.max_halvings), rows=rows)
    for s_name, scheme in sc.items():
        for v_name, scene in vs.items():
            for h in sorted(hs, reverse=True):
                r = one_run(scene, scheme, h, T, cap, a.max_halvings)
                r.update(scheme=s_name, variant=v_name)
                rows.append(r)
                print(f"{s_name:9s} {v_name:28s} h={h:<5g} {r['status']:11s} t={r['t_final']:<7.4g} "
                      f"H={r['H_final']:.6g} max dH/H0={r['max_step_increase_rel']:.2e} "
                      f"fails={r['newton_failures']} {r['wall_s']:.1f}s", flush=True)
                write_json(f"{a.out}.json", data)
    finish(data, rows, list(vs), list(sc), hs, T, a.out)


def finish(data, rows, vs, sc, hs, T, out):
    done = {(r["scheme"], r["variant"]) for r in rows}
    ran = {(r["scheme"], r["variant"], r["h"]) for r in rows}
    missing = [f"{s} / {v} / h={h:g}" for s in sc for v in vs for h in hs if (s, v, h) not in ran]
    complete = not missing
    if not complete:
        data["incomplete"] = "runs missing: " + "; ".join(missing)
    largest = {}
    for s_name in sc:
        ok = [r["h"] for r in rows if r["scheme"] == s_name and r["energy_nonincreasing"]]
        ran = [v for v in vs if (s_name, v) in done]
        all_ok = {v: sorted(r["h"] for r in rows if r["scheme"] == s_name and r["variant"] == v
                            and r["energy_nonincreasing"]) for v in ran}
        largest[s_name] = dict(
            largest_stable_nonincreasing_h_all_variants=max(
                (h for h in hs if ran and all(h in all_ok[v] for v in ran)), default=None),
            variants_run=ran,
            per_variant={v: (max(all_ok[v]) if all_ok[v] else None) for v in ran},
            stable_nonincreasing_at_every_h={v: len(all_ok[v]) == len(hs) for v in ran}, any=bool(ok))
    data["largest_stable_h"] = largest
    md = ["# Stability on the 2D L-shape", "",
          f"t in [0, {T:g}], consistent mass, refinement 1; {data['machine']['date']}; "
          f"{data['machine']['cpu_model']} ({data['machine']['cores']} cores; {data['machine']['conditions']}).",
          table(rows, list(vs), list(sc), hs), "## Largest h stable with non-increasing energy (all variants)", ""]
    for s_name, d in largest.items():
        md.append(f"- {s_name}: {d['largest_stable_nonincreasing_h_all_variants']} (per variant: {d['per_variant']})")
    if not complete:
        md += ["", f"**Incomplete:** {data['incomplete']}."]
    if data.get("note"):
        md += ["", f"**Note:** {data['note']}"]
    (RESULTS / f"{out}.md").write_text("\n".join(md) + "\n")
    write_json(f"{out}.json", data)
    plot(rows, vs, sc, RESULTS / f"{out}.png")


if __name__ == "__main__":
    main()
