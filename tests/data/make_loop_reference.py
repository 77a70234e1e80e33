"""Write loop_reference.npz: L-shape runs of the time loop as it was before issue #17.

    git worktree add /tmp/before 0e7253e   # jaxvisco 0.1: two time loops, 16-keyword simulate
    (build that tree's extension, e.g. from `pip wheel --no-deps /tmp/before`)
    PYTHONPATH=/tmp/before python tests/data/make_loop_reference.py

Uses jaxvisco 0.1's keywords on purpose (t_end, dt, schedules as lists): the file is the
forward result of the old loop, against which `test_time_integration` checks the one loop
of 0.2 (issue #17: equal to the Newton tolerance for every integrator).
"""

import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxvisco as jv  # noqa: E402

TIGHT = jv.NewtonKrylov(rtol=1e-12)
SCHEDULE = [(0.3, 0.1), (2.3, 1.0)]
CASES = {  # name: (integrator, t_end, dt)
    "eG1": (jv.eG(1), 2.3, SCHEDULE),
    "eG2": (jv.eG(2), 2.3, SCHEDULE),
    "eG1_halved": (jv.eG(1), 4.0, 2.0),  # every step of 2 is halved once
    "cG1": (jv.cG(1), 0.5, 0.1),
    "cG2": (jv.cG(2), 0.5, 0.1),
    "Midpoint": (jv.Midpoint(), 0.5, 0.1),
    "Newmark": (jv.Newmark(), 0.5, 0.1),
}
FIELDS = ("t", "x", "p", "energy", "dissipated", "linear_momentum", "angular_momentum", "rejections")


def main():
    scene = jv.scenes.lshape(dim=2, refinement=1)
    out = {"jaxvisco_version": np.array(jv.__version__)}
    for name, (scheme, t_end, dt) in CASES.items():
        sol = jv.simulate(scene, scheme, t_end=t_end, dt=dt, solver=TIGHT)
        assert sol.status == "done", (name, sol.status)
        for f in FIELDS:
            out[f"{name}/{f}"] = np.asarray(getattr(sol, f))
        print(name, "steps", int(sol.n_steps), "rejections", np.asarray(sol.rejections).tolist())
    path = pathlib.Path(__file__).with_name("loop_reference.npz")
    np.savez_compressed(path, **out)
    print("wrote", path)


if __name__ == "__main__":
    main()
