"""Each scene costs only what it uses: elastic vs viscous, saving every step vs only the end.

    python benchmarks/skip_cost.py [--quick]

eG(1) with h = 0.1 on the 2D L-shape (refinement 2; 1 with --quick): the paper's viscous
material against the same scene with no viscous branch (`viscous=False`: no internal
variable at all), each saving every step (`save_every=1`: positions, momenta and all
diagnostics every step) or only the last (`save_every=n`). ms per step after compilation
(median of repeats) and compile time. Writes benchmarks/results/skip_cost.json.
"""

import argparse
import time

from common import jv, machine, timed, write_json  # noqa: I001

import numpy as np  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default="skip_cost")
    a = p.parse_args(argv)
    r = 1 if a.quick else 2
    n = 20 if a.quick else 60
    h = 0.1
    rows = []
    data = dict(machine=machine(), settings=dict(scene=f"2D L-shape refinement {r}, consistent mass", integrator="eG(1)",
                                                 h=h, steps=n, repeats=3), rows=rows)
    for viscous in (True, False):
        scene = jv.scenes.lshape(2, r, viscous=viscous)
        for save_every in (1, n):
            def go():
                return jv.simulate(scene, jv.eG(1), t1=n * h, dt0=h, saveat=jv.SaveAt(every=save_every))

            sol, first, wall, times = timed(go, repeats=3)
            row = dict(material="viscous" if viscous else "elastic (no internal variable)",
                       save_every=save_every, frames=int(sol.n_saved), dofs=int(scene.mesh.n_nodes * 2),
                       gamma_unknowns=0 if scene.gamma0 is None else int(scene.gamma0.size // 9 * 6),
                       ms_per_step=1e3 * wall / n, compile_s=first - wall, times_s=times,
                       newton_per_step=float(np.mean(np.asarray(sol.newton_iterations))),
                       krylov_per_step=float(np.mean(np.asarray(sol.krylov_iterations))), status=sol.status)
            rows.append(row)
            print(row, flush=True)
            write_json(f"{a.out}.json", data)
    ms = {(x["material"].split()[0], x["save_every"]): x["ms_per_step"] for x in rows}
    data["ratios"] = dict(
        elastic_over_viscous_save_end=ms[("elastic", n)] / ms[("viscous", n)],
        save_every_step_over_save_end_viscous=ms[("viscous", 1)] / ms[("viscous", n)],
        save_every_step_over_save_end_elastic=ms[("elastic", 1)] / ms[("elastic", n)])
    data["measured_at"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    write_json(f"{a.out}.json", data)


if __name__ == "__main__":
    main()
