"""``jaxvisco run``: fixed steps (`_run`) or error-controlled ones (`_run_adaptive`)
into a new or resumed results file (`_open_writer`), a first Ctrl-C ending the run after
the chunk under way (`_StopOnSigint`), the file closed with the run's status whatever
happens (`_write_run`) and the closing report (`_report`).
"""

import math
import sys

import numpy as np

from ._checks import _warn_energy, print_notes
from ._chunked import chunk_size, run_adaptive_chunked, run_chunked, run_into
from ._options import _resume_args, _run_setup, _scene_file_options, flag, t1_name
from ._setup import parse_schedule


def _run(args):
    """`jaxvisco run`: its options resolved, then fixed steps (error-controlled ones in
    `_run_adaptive`)."""
    import jaxvisco as jv

    restart = None
    if args.resume is not None:
        args, restart = _resume_args(args)
    if args.dt is not None and args.schedule is not None:
        raise ValueError(f"give either {flag(args, 'dt')} or --schedule, not both.")
    if args.schedule is not None and (args.rtol is not None or args.atol is not None):
        raise ValueError("--schedule fixes the steps; --rtol/--atol choose them: give one of the two.")
    sf, schedule_origin = _scene_file_options(args)
    adaptive = args.rtol is not None or args.atol is not None
    if adaptive:
        return _run_adaptive(args, sf, restart)
    integrator, scene = _run_setup(args, sf, restart)
    steps, t_end = _fixed_steps(args, schedule_origin, restart)
    c = chunk_size([len(steps)], target=args.chunk, save_every=args.save_every)
    ts, state0, v0 = _continued_steps(args, restart, steps, t_end)
    print_notes(args)
    w = _open_writer(args, sf, scene, integrator, t_end, restart)
    return _write_run(args, integrator, w, lambda stop: run_chunked(
        scene, integrator, jv.StepTo(ts), chunk=c, commit_every=args.commit_every, save_every=args.save_every,
        writer=w, save_gamma=args.save_gamma, label=integrator.name, quiet=args.quiet, initial_state=state0,
        initial_velocity=v0, should_stop=stop, max_halvings=args.max_halvings,
        solver=None if sf is None else sf.root_finder))


def _fixed_steps(args, schedule_origin, restart):
    """The steps of a run with fixed steps (`--schedule`, else `--dt0`) and its final time;
    with `--resume` a `--t1` past the schedule's end continues its last step."""
    import jaxvisco as jv

    t0 = 0.0 if args.t0 is None else args.t0
    if args.schedule is not None:
        dt = parse_schedule(args.schedule)
        schedule_name = schedule_origin or f"--schedule {args.schedule!r}"
        t_end = args.t_end if args.t_end is not None else dt[-1][0]
        if t_end > dt[-1][0]:
            if restart is None:
                raise ValueError(f"{schedule_name} ends at t = {dt[-1][0]:g}, before {flag(args, 't_end')} "
                                 f"{t_end:g}: add a piece that reaches it, e.g. "
                                 f"'{args.schedule},{t_end:g}:{dt[-1][1]:g}'.")
            dt[-1] = (math.inf, dt[-1][1])  # --resume --t1: the last step continues
        try:
            steps = jv.StepTo.from_schedule(t0, t_end, dt, t1_name=t1_name(args))
        except ValueError as e:
            raise ValueError(f"{schedule_name}: {e}") from None
    else:
        t_end = 1.0 if args.t_end is None else args.t_end
        steps = jv.StepTo.from_schedule(t0, t_end, 0.1 if args.dt is None else args.dt, t1_name=t1_name(args))
    return steps, t_end


def _continued_steps(args, restart, steps, t_end):
    """The step times still to take and the state and predictor velocity they start from:
    all of `steps` from the scene's initial state, or with `--resume` the rest of them from
    the stored run's last state (checked to lie on `steps`)."""
    state0, v0, ts = None, None, steps.ts
    if restart is not None:
        done = restart.n_steps
        if done >= len(steps) or restart.t >= t_end * (1 - 1e-12):
            raise ValueError(f"{args.resume!r} already reaches t = {restart.t:.6g} ({t1_name(args)} = {t_end:.6g}); "
                             f"give a later {flag(args, 't_end')} to continue it.")
        if not math.isclose(ts[done], restart.t, rel_tol=1e-9, abs_tol=1e-12):
            raise ValueError(f"{args.resume!r}: its {done} steps end at t = {restart.t:.17g}, but the stored schedule "
                             f"puts step {done} at t = {ts[done]:.17g}; it cannot be continued with {flag(args, 't_end')} "
                             f"{t_end:g}.")
        ts = np.concatenate([[restart.t], ts[done + 1:]])
        state0, v0 = restart.state, restart.velocity
    return ts, state0, v0


def _run_adaptive(args, sf, restart):
    """`jaxvisco run` with error-controlled steps (--rtol/--atol)."""
    import jaxvisco as jv
    from jaxvisco._tools._resume import largest_strain_in, last_step_size

    rtol = args.rtol if args.rtol is not None else args.atol
    atol = args.atol if args.atol is not None else rtol
    try:
        controller = jv.PIDController(rtol=rtol, atol=atol)
    except ValueError as e:
        raise ValueError(f"--rtol/--atol: {e}") from None
    integrator, scene = _run_setup(args, sf, restart)
    t_end = 1.0 if args.t_end is None else args.t_end
    t0, state0, v0, dt0 = (0.0 if args.t0 is None else args.t0), None, None, args.dt
    if not t_end > t0:
        raise ValueError(f"{t1_name(args)} must be greater than t0 = {t0!r}, got {t1_name(args)} = {t_end!r}.")
    if restart is not None:
        if restart.t >= t_end * (1 - 1e-12):
            raise ValueError(f"{args.resume!r} already reaches t = {restart.t:.6g} ({t1_name(args)} = {t_end:.6g}); "
                             f"give a later {flag(args, 't_end')} to continue it.")
        t0, state0, v0 = restart.t, restart.state, restart.velocity
        h = last_step_size(args.resume)
        dt0 = dt0 if h is None else h
        # atol on the internal variable in units of the largest strain so far, as the
        # run's chunks carried it (`PIDController.strain_scale`): from the stored frames
        controller = controller.continued(largest_strain_in(args.resume, scene))
    print_notes(args)
    w = _open_writer(args, sf, scene, integrator, t_end, restart)
    return _write_run(args, integrator, w, lambda stop: run_adaptive_chunked(
        scene, integrator, controller, t0, t_end, dt0=dt0, chunk=args.chunk, save_every=args.save_every, writer=w,
        save_gamma=args.save_gamma, label=integrator.name, quiet=args.quiet, initial_state=state0,
        initial_velocity=v0, should_stop=stop, solver=None if sf is None else sf.root_finder))


def _write_run(args, integrator, w, go):
    """Run `go(should_stop)` into the open writer `w`, close it with the run's status
    (also when interrupted or failing), and report."""
    def run():
        with _StopOnSigint(args.quiet) as stop:
            return go(stop)

    r = run_into(w, run)
    return _report(args, integrator, r["status"], r)


class _StopOnSigint:
    """First Ctrl-C: finish the chunk under way, write it, stop ("interrupted"); a second
    one interrupts at once (KeyboardInterrupt)."""

    def __init__(self, quiet):
        self.flag, self.quiet, self.old = False, quiet, None

    def __call__(self):
        return self.flag

    def _handler(self, signum, frame):
        import signal

        self.flag = True
        signal.signal(signal.SIGINT, self.old)
        print("jaxvisco: interrupt: stopping after the chunk under way (Ctrl-C again to stop at once)",
              file=sys.stderr, flush=True)

    def __enter__(self):
        import signal

        try:
            self.old = signal.signal(signal.SIGINT, self._handler)
        except ValueError:  # not the main thread
            self.old = None
        return self

    def __exit__(self, *exc):
        import signal

        if self.old is not None:
            signal.signal(signal.SIGINT, self.old)


def _open_writer(args, sf, scene, integrator, t_end, restart):
    """The results writer of a run: a new file, or the resumed one appended to."""
    import jaxvisco as jv

    params = {k: v for k, v in vars(args).items() if k not in ("func", "deprecated", "spelled")}
    params.update(t_end=t_end, **({} if sf is not None else dict(dim=scene.dim)))
    if restart is not None:
        w = jv.ResultsWriter(args.out, append=True, attrs={"parameters": params})
    else:
        label = "scenefile:" + args.scene if sf is not None else ("mesh:" + args.mesh) if args.mesh else "lshape"
        attrs = dict(scene=label, integrator=integrator.describe(), parameters=params)
        w = jv.ResultsWriter(args.out, scene, attrs, overwrite=args.overwrite)
    return w


def _report(args, integrator, status, r):
    """The closing line of a run, and its exit status (a failed run raises)."""
    import jaxvisco as jv

    saved = jv.read_results(args.out)
    H = saved["energy"]
    print(f"{integrator.name}: status={status} H0={H[0]:.8g} H_end={H[-1]:.8g} t={saved['t'][-1]:.6g} "
          f"steps={len(saved['step_t'])} (this call {r['steps']}) wall={r['wall']:.1f}s -> {args.out}", flush=True)
    _warn_energy(saved, integrator.name)
    if status == "failed":
        raise jv.SolverError(f"{integrator.name}: the step after t = {r['t_last']:.6g} did not converge; "
                             f"results up to it are in {args.out}", r["t_last"], r["state"], None)
    if status == "interrupted":
        print(f"jaxvisco: interrupted at t = {r['t_last']:.6g}; continue with: jaxvisco run --resume {args.out}",
              file=sys.stderr, flush=True)
        return 130
    return 0
