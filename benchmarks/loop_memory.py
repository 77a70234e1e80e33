"""XLA's memory analysis of the compiled time loop: deterministic, no timing.

    python benchmarks/loop_memory.py [--refinements 4,6] [--element hex8] [--preconditioner amg]

For each refinement of the 3D L-shape (eG(1), h = 0.1, consistent mass), lowers and
compiles the time loop that `simulate` would run (without running it) and prints XLA's
temporary buffers, arguments and outputs (`Compiled.memory_analysis()`), per run and per
position unknown. The temporary buffers are the largest part of a run's peak memory on
big meshes and, unlike the peak RSS, do not vary between identical runs, so a change
that is meant to save memory can be checked with one compile per side.
To see which arrays make them up: XLA_FLAGS="--xla_dump_to=DIR
--xla_dump_hlo_module_re=.*jit__run.*" and read DIR/*buffer-assignment.txt.
"""

import argparse
import resource
import time

from common import jv, lshape  # noqa: I001

from jaxvisco._integrate import _simulate


class _Captured(Exception):
    pass


def loop_arguments(scene, solver, steps=2, h=0.1):
    """The arguments `simulate` passes to its compiled loop (captured, not run)."""
    captured = {}
    run = _simulate._run

    def capture(*args, **kwargs):
        captured["call"] = (args, kwargs)
        raise _Captured

    _simulate._run = capture
    try:
        jv.simulate(scene, jv.eG(1), t1=steps * h, dt0=h, saveat=jv.SaveAt(every=steps), root_finder=solver)
    except _Captured:
        pass
    finally:
        _simulate._run = run
    return captured["call"]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--refinements", default="4")
    p.add_argument("--element", default="hex8")
    p.add_argument("--preconditioner", default="amg", choices=("lu", "amg"))
    p.add_argument("--restart", type=int, default=None, help="GMRES(restart=) (default: the solver's)")
    a = p.parse_args(argv)
    solver = jv.NewtonKrylov(linear_solver=jv.GMRES(preconditioner=a.preconditioner, restart=a.restart))
    for r in map(int, a.refinements.split(",")):
        scene = lshape(3, r, element=a.element, mass="consistent")
        args, kwargs = loop_arguments(scene, solver)
        t0 = time.perf_counter()
        lowered = _simulate._run.lower(*args, **kwargs)
        t1 = time.perf_counter()
        m = lowered.compile().compiled.memory_analysis()
        t2 = time.perf_counter()
        n = scene.mesh.n_nodes * 3
        mb = lambda b: b / 2**20  # noqa: E731
        print(f"{a.element} r{r} {a.preconditioner}: {n} unknowns, temporary {mb(m.temp_size_in_bytes):.1f} MB "
              f"({m.temp_size_in_bytes / n / 1e3:.2f} KB per unknown), arguments {mb(m.argument_size_in_bytes):.1f} MB, "
              f"outputs {mb(m.output_size_in_bytes):.1f} MB, generated code {mb(m.generated_code_size_in_bytes):.1f} MB; "
              f"lowered in {t1 - t0:.1f} s, compiled in {t2 - t1:.1f} s; process peak RSS so far "
              f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB", flush=True)


if __name__ == "__main__":
    main()
