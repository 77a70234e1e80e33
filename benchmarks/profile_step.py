"""Where a jaxvisco step spends its time: host sparse LU (factor, solve) vs the rest.

    python benchmarks/profile_step.py [--quick]
    python benchmarks/profile_step.py --dim 3 --refinement 4 --element hex8 --mass consistent \
        --h 0.1 --steps 5 --schemes "eG(1)" --out profile_step_3d

eG(1) and eG(2) on the 2D L-shape (refinement 1, lumped mass as in work_precision.py),
h = 0.05, after compilation (other scenes by the options). The sparse factorizations and
solves run on the host through `jax.pure_callback` (`HostLU.factor`, `HostLU.solve`), called synchronously from XLA's
threads (which cProfile does not see); this script wraps those two methods with timers
before anything is traced, so their share of the wall time is measured. The rest is the
compiled XLA program (residuals, JVPs, GMRES, tangent assembly) and callback overhead.
Writes benchmarks/results/profile_step.json.
"""

import argparse
import collections
import time

from common import jv, lshape, machine, schemes, write_json  # noqa: I001

import numpy as np  # noqa: E402

from jaxvisco._solver import _sparse  # noqa: E402

TIMES = collections.defaultdict(lambda: [0, 0.0])


def _timed_method(name):
    inner = getattr(_sparse.HostLU, name)

    def wrapper(self, *args, **kwargs):
        t0 = time.perf_counter()
        try:
            return inner(self, *args, **kwargs)
        finally:
            TIMES[name][0] += 1
            TIMES[name][1] += time.perf_counter() - t0

    return wrapper


for _name in ("factor", "solve"):
    setattr(_sparse.HostLU, _name, _timed_method(_name))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--dim", type=int, default=2)
    p.add_argument("--refinement", type=int, default=1)
    p.add_argument("--element", default=None, help="hex8 or tet4 (3D); the mesh's default if omitted")
    p.add_argument("--mass", default="lumped", choices=("lumped", "consistent"))
    p.add_argument("--steps", type=int, default=None)
    p.add_argument("--h", type=float, default=0.05)
    p.add_argument("--schemes", default="eG(1),eG(2)")
    p.add_argument("--out", default="profile_step")
    a = p.parse_args(argv)
    n, h = a.steps or (40 if a.quick else 200), a.h
    scene = lshape(a.dim, a.refinement, element=a.element, mass=a.mass)
    rows = []
    data = dict(machine=machine(), settings=dict(
        scene=f"{a.dim}D L-shape r{a.refinement}{' ' + a.element if a.element else ''}, {a.mass} mass",
        dofs=int(scene.mesh.n_nodes * a.dim), h=h, steps=n), rows=rows)
    known = schemes()
    for name in a.schemes.split(","):
        if name not in known:
            raise SystemExit(f"unknown scheme {name!r}; accepted: {sorted(known)}")
        scheme = known[name]
        def go():
            return jv.simulate(scene, scheme, t1=n * h, dt0=h, saveat=jv.SaveAt(every=n))

        go()  # compile
        TIMES.clear()
        t0 = time.perf_counter()
        sol = go()
        wall = time.perf_counter() - t0
        host = {k: dict(calls=v[0], seconds=v[1]) for k, v in TIMES.items()}
        host_s = sum(v["seconds"] for v in host.values())
        row = dict(scheme=name, wall_s=wall, ms_per_step=1e3 * wall / n, host_lu=host, host_lu_fraction=host_s / wall,
                   newton_per_step=float(np.mean(np.asarray(sol.newton_iterations))),
                   krylov_per_step=float(np.mean(np.asarray(sol.krylov_iterations))))
        rows.append(row)
        print(row, flush=True)
        write_json(f"{a.out}.json", data)


if __name__ == "__main__":
    main()
