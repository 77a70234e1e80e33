"""Batches of runs: `jax.lax.map` against `jax.vmap` against separate calls.

    python benchmarks/batch_cost.py [--quick]

A batch of eG(1) runs on the 2D L-shape (refinement 1), members differing in eta_dev and
the initial velocity scale, t in [0, 2] at h = 0.1 (--quick: 4 members, t in [0, 1]).
Three ways to run it: one jitted call per member (the reference cost), one program that
maps over the batch with `jax.lax.map` (what `jv.sharded_map` does by default on each
device), and one program that advances all members together with `jax.vmap`. Under vmap
the solver's `lax.cond`s become selects, so every member pays for both branches (tangent
formation, GMRES) on every Newton pass. Wall time after compilation (median of repeats)
and compile time; the largest difference of the final positions between the ways.
Writes benchmarks/results/batch_cost.json.
"""

import argparse
import time

from common import jv, machine, timed, write_json  # noqa: I001

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--members", type=int, default=None)
    p.add_argument("--out", default="batch_cost")
    a = p.parse_args(argv)
    n = a.members or (4 if a.quick else 8)
    t_end, h = (1.0, 0.1) if a.quick else (2.0, 0.1)
    scene = jv.scenes.lshape(dim=2, refinement=1)
    etas = jnp.asarray(np.geomspace(2e4, 3e5, n))
    vs = jnp.asarray(np.linspace(0.5, 1.5, n))

    def run(eta_dev, vscale):
        sc = jv.with_parameters(scene, {"eta_dev": eta_dev})
        sc = eqx.tree_at(lambda s: s.v0, sc, vscale * sc.v0)
        s = jv.simulate(sc, jv.eG(1), t1=t_end, dt0=h)
        return s.x[-1], jnp.sum(s.newton_iterations)

    single = jax.jit(run)
    mapped = jax.jit(lambda e, v: jax.lax.map(lambda ev: run(*ev), (e, v)))
    vmapped = jax.jit(jax.vmap(run))
    ways = {
        "separate calls": lambda: [jax.block_until_ready(single(etas[i], vs[i])) for i in range(n)],
        "lax.map": lambda: jax.block_until_ready(mapped(etas, vs)),
        "vmap": lambda: jax.block_until_ready(vmapped(etas, vs)),
    }
    rows, finals = [], {}
    data = dict(machine=machine(), settings=dict(scene="2D L-shape refinement 1 (jaxvisco.scenes.lshape)",
                                                 integrator="eG(1)", t_end=t_end, h=h, members=n, repeats=3),
                rows=rows)
    for name, go in ways.items():
        out, first, wall, times = timed(go, repeats=3)
        if name == "separate calls":
            x = np.stack([np.asarray(o[0]) for o in out])
            newton = int(sum(int(o[1]) for o in out))
        else:
            x, newton = np.asarray(out[0]), int(np.sum(np.asarray(out[1])))
        finals[name] = x
        row = dict(way=name, wall_s=wall, ms_per_member_step=1e3 * wall / (n * round(t_end / h)),
                   compile_s=first - wall, times_s=times, newton_iterations=newton)
        rows.append(row)
        print(row, flush=True)
        write_json(f"{a.out}.json", data)
    ref = finals["separate calls"]
    for row in rows:
        row["max_abs_dx_vs_separate"] = float(np.max(np.abs(finals[row["way"]] - ref)))
    w = {r["way"]: r["wall_s"] for r in rows}
    data["ratios"] = dict(vmap_over_lax_map=w["vmap"] / w["lax.map"],
                          lax_map_over_separate=w["lax.map"] / w["separate calls"])
    data["measured_at"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    write_json(f"{a.out}.json", data)


if __name__ == "__main__":
    main()
