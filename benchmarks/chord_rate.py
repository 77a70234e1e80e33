"""What sets the rate of the chord iterations: where the stored tangent was formed.

    python benchmarks/chord_rate.py [--k 1] [--refinement 4] [--h 0.1] [--t 2.0]

Issue #16's step-cost target (2D r4 lumped, eG(1), h = 0.1: <= 25 right-hand sides per
step, 37 measured) is dominated by the chord iterations (6.6 per step). This takes the
step from t (after a run of constant steps to t) and runs chord iterations from the
predictor, U <- U - T^{-1} R(U), with the condensed tangent T formed (a) at the
predictor, (b) at the step's converged solution (Newton-Krylov from the predictor,
rtol 1e-12), and records the scaled residual (Newton's max norm over the step's momentum
scale) and the largest position distance from the solution per iteration. If T were an
approximate Jacobian, (b) would contract at a fixed rate too; it is exact, so (b)
converges superlinearly and (a) contracts at a rate set by the distance between the
predictor and the solution. A stored tangent (formed at an earlier step, carried along
the body's rotation) behaves like (a). Counts only, deterministic. Writes
benchmarks/results/chord_rate.json.
"""

import argparse

from common import jv, lshape, machine, write_json  # noqa: I001

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from jaxvisco._solver._newton import NewtonKrylov, _norm, _scale, solve_step  # noqa: E402
from jaxvisco._solver._tangent import body_rotation, empty_tangent, form_tangent, schur_solve  # noqa: E402
from jaxvisco._time_element._step import make_context, predictor, residual  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--k", type=int, default=1)
    p.add_argument("--refinement", type=int, default=4)
    p.add_argument("--h", type=float, default=0.1)
    p.add_argument("--t", type=float, default=2.0)
    p.add_argument("--iterations", type=int, default=8)
    a = p.parse_args(argv)
    scene, scheme = lshape(2, a.refinement, mass="lumped"), jv.eG(a.k)
    sol = jv.simulate(scene, scheme, 0.0, a.t, a.h, saveat=jv.SaveAt(gamma=True))
    state = sol.state(-1)
    ctx = make_context(scene, state, jnp.asarray(a.t), jnp.asarray(a.h))
    U0 = predictor(scheme, scene, ctx, sol.end_velocity)
    rot = body_rotation(scene, state.x)
    r = eqx.filter_jit(lambda: solve_step(NewtonKrylov(rtol=1e-12, chord=0), scheme, scene, ctx, U0,
                                          empty_tangent(scheme, scene)))()
    res = eqx.filter_jit(lambda U: residual(scheme, scene, ctx, U))
    tangent = eqx.filter_jit(lambda U: form_tangent(scheme, scene, ctx, U, rot))
    solve = eqx.filter_jit(lambda T, R: schur_solve(scheme, scene, ctx, T, jax.tree_util.tree_map(jnp.negative, R), rot))
    sx = _scale(ctx, scene, res(U0))
    rows = []
    for where, at in (("predictor", U0), ("solution", r.U)):
        T, U, norms, dist = tangent(at), U0, [], []
        for _ in range(a.iterations):
            R = res(U)
            norms.append(float(_norm(R, sx)))
            dist.append(float(jnp.max(jnp.abs(U.x - r.U.x))))
            U = jax.tree_util.tree_map(jnp.add, U, solve(T, R))
        rows.append(dict(tangent_formed_at=where, scaled_residual=norms, max_position_distance=dist))
        print(f"tangent at the {where}: " + " ".join(f"{n:.1e}" for n in norms), flush=True)
    write_json("chord_rate.json", dict(
        machine=machine(), settings=dict(scene=f"2D L-shape r{a.refinement}, lumped mass", scheme=scheme.name,
                                         h=a.h, t=a.t, solution="NewtonKrylov(rtol=1e-12, chord=0) from the predictor",
                                         newton_iterations_to_solution=int(r.iterations)),
        rows=rows))


if __name__ == "__main__":
    main()
