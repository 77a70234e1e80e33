"""Command line: ``jaxvisco paper | run | plot | scene-template``.

``jaxvisco paper`` reproduces the L-shape comparison of Groß & Betsch (2005) (cG(1)
against eG(1), a step-size change at t = 20 and large steps from the outset), ``jaxvisco
run`` integrates a scene file (``jaxvisco run SCENE.toml``, see `_scenefile`), a built-in
L-shape or a mesh file with any integrator, ``jaxvisco plot`` draws energy, energy
balance and momenta from a results file, ``jaxvisco scene-template`` prints a commented
scene file. Every subcommand has ``--help``. Runs are advanced in equal-sized chunks (one
compiled program reused) so that progress can be printed and the results file grows as
the run goes.
"""

import argparse
import math
import os
import sys
import time

import numpy as np

PAPER_T = 60.0
QUICK_T = 24.0


class _CLIError(Exception):
    pass


# ---------------------------------------------------------------- running in chunks


def parse_schedule(text):
    """``"20:0.1,40:1.0"`` -> ``[(20.0, 0.1), (40.0, 1.0)]``."""
    pieces = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        try:
            a, b = part.split(":")
            pieces.append((float(a), float(b)))
        except ValueError:
            raise ValueError(f"bad --schedule entry {part!r}: expected T_UNTIL:DT, e.g. '20:0.1,40:1.0'.") from None
    if not pieces:
        raise ValueError(f"empty --schedule {text!r}: expected T_UNTIL:DT pairs, e.g. '20:0.1,40:1.0'.")
    return pieces


def chunk_size(lengths, target=50, save_every=1):
    """A chunk length (in steps) that divides every run length if possible, so all chunks
    of all runs share one compiled program; otherwise `target` (where `simulate` has no
    `max_steps`, the shorter last chunk compiles once more)."""
    g = 0
    for n in lengths:
        g = math.gcd(g, int(n))
    best = 0
    for c in range(1, min(g, target) + 1):
        if g % c == 0 and c % save_every == 0:
            best = c
    if best >= max(1, target // 8):
        return best
    c = max(save_every, (target // save_every) * save_every)
    return min(c, max(lengths))


def run_chunked(scene, integrator, steps, chunk=50, commit_every=5.0, save_every=1, solver=None, writer=None,
                save_gamma=False, label="", quiet=False, stream=None, initial_state=None, initial_velocity=None,
                should_stop=None, max_halvings=6):
    """Integrate over the steps of `steps` (a `StepTo`) in chunks, committing each one.

    A new `writer` first commits frame 0 (before anything compiles), so a run killed at
    any moment can be resumed. Every chunk is one call of one compiled program (capacity
    `chunk` steps) that continues from the previous chunk's last state and predictor
    velocity, and is committed to `writer` when it returns. With `commit_every` > 0
    (seconds) the chunks are sized from the measured time per step so that a commit
    follows at least about every `commit_every` seconds: the first chunk of a process is
    `save_every` steps (it also compiles), later ones as many as fit, at most `chunk`.
    With `commit_every` = 0 every chunk has `chunk` steps, so a run split at a chunk
    boundary repeats the uninterrupted one exactly (the reused tangent that
    preconditions the Krylov solver starts afresh at every chunk, so other splits agree
    to the Newton tolerance). `initial_state`/`initial_velocity` continue a saved run.
    `should_stop()` is asked after every chunk; when true the run ends "interrupted".

    Returns a dict: `status`, `steps` (taken), `newton` (total iterations), `wall`,
    `state` (last state), `t_last`.
    """
    import jaxvisco as jv

    stream = stream or sys.stderr
    solver = solver or jv.NewtonKrylov()
    ts = np.asarray(steps.ts)
    n = len(ts) - 1
    state, v = initial_state, initial_velocity
    start = time.perf_counter()
    if writer is not None and writer.n_frames == 0:
        writer.write_initial_state(float(ts[0]), state, v)
    status, i, newton, per_step = "done", 0, 0, None
    if not quiet:
        print(f"{label}: {n} steps; frame 0 written, the first chunk compiles (~10-60 s)", file=stream, flush=True)
    while i < n:
        m = chunk
        if commit_every > 0:
            m = save_every if per_step is None else int(commit_every / max(per_step, 1e-9))
            m = max(save_every, min(chunk, m) // save_every * save_every)
        m = min(m, n - i)
        t_call = time.perf_counter()
        sol = jv.simulate(scene, integrator, stepsize_controller=jv.StepTo(ts[i:i + m + 1], max_halvings=max_halvings),
                          saveat=jv.SaveAt(every=save_every, gamma=True), solver=solver, initial_state=state,
                          throw=False, initial_velocity=v, max_steps=chunk)
        per_step = (time.perf_counter() - t_call) / m  # the first call also compiles: an overestimate
        if writer is not None:
            writer.append(sol, skip_first=True, gamma=save_gamma)
        ns = int(len(np.asarray(sol.step_t)))
        i += ns
        its = np.asarray(sol.newton_iterations)
        newton += int(its.sum())
        state, v = sol.state(-1), sol.end_velocity
        H = float(np.asarray(sol.energy)[-1])
        if not quiet:
            print(f"{label}: t = {float(np.asarray(sol.t)[-1]):9.4f}  step {i:6d}/{n}  newton/step "
                  f"{its.mean() if ns else 0:4.1f}  H = {H:.8g}", file=stream, flush=True)
        if sol.status in ("failed", "equilibrium"):
            status = sol.status
            break
        if should_stop is not None and should_stop() and i < n:
            status = "interrupted"
            break
    state = jv.State(np.asarray(state.x), np.asarray(state.p), None if state.gamma is None else np.asarray(state.gamma))
    return dict(status=status, steps=i, newton=newton, wall=time.perf_counter() - start, state=state,
                t_last=float(ts[i]) if status != "failed" else float(np.asarray(sol.t)[-1]))


def run_adaptive_chunked(scene, integrator, controller, t0, t_end, dt0=None, chunk=50, save_every=1, solver=None,
                         writer=None, save_gamma=False, label="", quiet=False, stream=None, initial_state=None,
                         initial_velocity=None, should_stop=None):
    """`run_chunked` for error-controlled steps (`controller`, a `PIDController`): calls
    of at most `chunk` accepted steps (one compiled program), each committed to
    `writer`, each continuing from the previous one's state, predictor velocity and last
    accepted step. Returns the dict of `run_chunked`, with `h_last`."""
    import jaxvisco as jv

    stream = stream or sys.stderr
    solver = solver or jv.NewtonKrylov()
    state, v, t, h = initial_state, initial_velocity, float(t0), dt0
    start = time.perf_counter()
    if writer is not None and writer.n_frames == 0:
        writer.write_initial_state(t, state, v)
    status, n, newton, rejected = "done", 0, 0, 0
    if not quiet:
        print(f"{label}: adaptive steps (rtol = {float(controller.rtol):g}, atol = {float(controller.atol):g}) to "
              f"t = {t_end:g}; frame 0 written, the first chunk compiles (~10-60 s)", file=stream, flush=True)
    while True:
        sol = jv.simulate(scene, integrator, t, t_end, h, saveat=jv.SaveAt(every=save_every, gamma=True), solver=solver,
                          initial_state=state, throw=False, initial_velocity=v, max_steps=chunk,
                          stepsize_controller=controller)
        if writer is not None:
            writer.append(sol, skip_first=True, gamma=save_gamma)
        ns = int(len(np.asarray(sol.step_t)))
        n += ns
        its = np.asarray(sol.newton_iterations)
        newton += int(its.sum())
        rejected += int(np.asarray(sol.rejections).sum())
        if ns:
            state, v, t, h = sol.state(-1), sol.end_velocity, float(np.asarray(sol.step_t)[-1]), \
                float(np.asarray(sol.step_h)[-1])
        if not quiet:
            print(f"{label}: t = {t:9.4f}  steps {n:6d} ({rejected} rejected)  h = {h if h else float('nan'):.4g}  "
                  f"newton/step {its.mean() if ns else 0:4.1f}  H = {float(np.asarray(sol.energy)[-1]):.8g}",
                  file=stream, flush=True)
        if sol.status != "max_steps":
            status = sol.status
            break
        if should_stop is not None and should_stop():
            status = "interrupted"
            break
    state = jv.State(np.asarray(state.x), np.asarray(state.p), None if state.gamma is None else np.asarray(state.gamma))
    return dict(status=status, steps=n, newton=newton, wall=time.perf_counter() - start, state=state, t_last=t,
                h_last=h)


# ---------------------------------------------------------------- scenes and integrators


def make_integrator(name, order=1):
    import jaxvisco as jv

    key = str(name).strip().lower()
    if key in ("cg", "eg"):
        if not isinstance(order, int) or order < 1:
            raise ValueError(f"--order must be an integer >= 1, got {order!r}.")
        return jv.cG(order) if key == "cg" else jv.eG(order)
    if key == "newmark":
        return jv.Newmark()
    if key == "midpoint":
        return jv.Midpoint()
    raise ValueError(f"unknown integrator {name!r}; choose cG, eG, Newmark or Midpoint.")


def make_scene(dim=2, refinement=1, element=None, mesh=None, lam=None, mu=None, density=None, eta_dev=None,
               eta_vol=None):
    """The paper's L-shape (or a mesh file with the paper's material and rigid initial
    velocity v0 = v_T + omega x X), with any parameter overridden."""
    import jax.numpy as jnp

    import jaxvisco as jv

    p = dict(jv.scenes.PAPER)
    for k, v in dict(lam=lam, mu=mu, density=density, eta_dev=eta_dev, eta_vol=eta_vol).items():
        if v is not None:
            if not (v > 0 and math.isfinite(v)) and not (k.startswith("eta") and v == math.inf):
                raise ValueError(f"--{k.replace('_', '-')} must be positive, got {v!r}.")
            p[k] = v
    if mesh is None:
        if dim not in (2, 3):
            raise ValueError(f"--dim must be 2 or 3, got {dim!r}.")
        if not isinstance(refinement, int) or refinement < 1:
            raise ValueError(f"--refinement must be an integer >= 1, got {refinement!r}.")
        return jv.scenes.lshape(dim=dim, refinement=refinement, element=element, lam=p["lam"], mu=p["mu"],
                                density=p["density"], eta_dev=p["eta_dev"], eta_vol=p["eta_vol"])
    m = jv.Mesh.read(mesh)
    nh = jv.NeoHooke(lam=p["lam"], mu=p["mu"])
    material = jv.ReeseGovindjee(nh, nh, eta_dev=p["eta_dev"], eta_vol=p["eta_vol"])
    X = jnp.asarray(m.points)
    vT = jnp.asarray(p["v_translation"], dtype=float)
    w = jnp.asarray(p["omega"], dtype=float)
    if m.dim == 2:
        v0 = vT[:2] + w[2] * jnp.stack([-X[:, 1], X[:, 0]], axis=-1)
    else:
        v0 = vT + jnp.cross(w, X)
    return jv.Scene(m, material, p["density"], velocities=v0)


# ---------------------------------------------------------------- checks on a finished run


def energy_warning(t, energy, dissipated, external_work, label, tol=0.05):
    """A one-line warning when the integrator created energy, else None.

    The energy created by time t is ``H(t) + dissipated(t) - external_work(t) - H(0)``
    (zero for an exact energy balance, negative where a scheme dissipates numerically);
    nothing supplies it. Its maximum over the frames is compared with `tol` times the
    energy scale ``max(|H(0)|, max |external_work|)``. An energy-stable scheme (eG(k))
    never warns; cG(k), Newmark or the midpoint rule do with a step too large for them.
    Frames with non-finite values are ignored.
    """
    t, H = np.asarray(t, dtype=float), np.asarray(energy, dtype=float)
    D = np.broadcast_to(np.asarray(dissipated, dtype=float), H.shape)
    W = np.broadcast_to(np.asarray(external_work, dtype=float), H.shape)
    if H.size == 0:
        return None
    H0 = H[0]
    created = H + D - W - H0
    ok = np.isfinite(created) & np.isfinite(t)
    if not np.isfinite(H0) or not ok.any():
        return None
    scale = max(abs(H0), float(np.max(np.abs(W[ok]))))
    i = int(np.flatnonzero(ok)[np.argmax(created[ok])])
    if scale == 0.0 or not created[i] > tol * scale:
        return None
    rose = f"H rose {H[i] / H0:.3g}-fold" if H0 > 0 else "H rose"
    unit = "|H0|" if scale == abs(H0) else "max |external work|"
    return (f"{label}: {rose} from H0 = {H0:.6g} to {H[i]:.6g} at t = {t[i]:.6g}; the integrator created an energy "
            f"of {created[i]:.3g} ({created[i] / scale:.3g} x {unit}) that neither the loads' work nor the dissipation "
            "supplies, so the step is likely too large for this scheme (eG(k) is energy-stable).")


# ---------------------------------------------------------------- subcommands


def _paper(args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    results = []
    for scheme_name, integrator in integrators:
        for sched_name, steps in runs:
            label = f"{scheme_name}_{sched_name}"
            path = paths[label]
            attrs = dict(scene="lshape", refinement=1, integrator=integrator.describe(),
                         parameters=dict(schedule=schedule if sched_name == "schedule" else [(T, 1.0)], t_end=T))
            w = jv.ResultsWriter(path, scene, attrs, overwrite=args.overwrite)
            status = "failed"
            try:
                r = run_chunked(scene, integrator, steps, chunk=c, writer=w, label=label, quiet=args.quiet)
                status = r["status"]
            except KeyboardInterrupt:
                status = "interrupted"
                raise
            finally:
                w.close(status=status)
            saved = jv.read_results(path)
            r.update(t=saved["t"], energy=saved["energy"])
            results.append((scheme_name, sched_name, r))
            sched_txt = "h=0.1->1.0@t=20" if sched_name == "schedule" else "h=1.0"
            print(f"{scheme_name:4s} {sched_txt:16s} status={r['status']:11s} H0={r['energy'][0]:.6g} "
                  f"H_end={r['energy'][-1]:.6g} (t={r['t_last']:.4g}) steps={r['steps']} wall={r['wall']:.1f}s",
                  flush=True)
            _warn_energy(saved, label)
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
    fig.savefig(os.path.join(out, "energy.png"), dpi=120)
    plt.close(fig)
    if not args.quiet:
        print(f"wrote {out}/energy.png and {len(results)} results files", file=sys.stderr)
    return 0


def _warn_energy(r, label):
    """Print `energy_warning` for the results `r` (`read_results`) to stderr, if it warns."""
    H = r["energy"]
    msg = energy_warning(r["t"], H, r.get("dissipated", np.zeros_like(H)), r.get("external_work", np.zeros_like(H)),
                         label)
    if msg is not None:
        print(f"jaxvisco: warning: {msg}", file=sys.stderr, flush=True)


_RESUMABLE = ("t_end", "quiet", "resume")


def _resume_args(args):
    """The options of the run stored in `args.resume`, with `--t-end` and `--quiet`
    taken from the command line."""
    import jaxvisco as jv

    restart = jv.read_restart(args.resume)
    if args.scene is not None:
        raise ValueError(f"with --resume the scene comes from the results file; give no scene file "
                         f"({args.scene!r}), only --t-end and --quiet.")
    given = {k: v for k, v in vars(args).items() if k not in ("func",) + _RESUMABLE}
    defaults = {k: v for k, v in vars(build_parser().parse_args(["run"])).items() if k in given}
    changed = sorted(k for k, v in given.items() if v != defaults[k])
    if changed:
        raise ValueError(f"with --resume the run's options come from the results file; only --t-end and --quiet "
                         f"may be given, got --{', --'.join(c.replace('_', '-') for c in changed)}.")
    params = restart.attrs.get("parameters")
    if not isinstance(params, dict) or "integrator" not in params:
        raise ValueError(f"{args.resume!r} was not written by `jaxvisco run` (no run parameters stored); "
                         "continue it from Python with jaxvisco.resume.")
    stored = argparse.Namespace(**{**defaults, **{k: v for k, v in params.items() if k in defaults}})
    stored.t_end = params.get("t_end") if args.t_end is None else args.t_end
    stored.quiet, stored.out, stored.resume = args.quiet, args.resume, args.resume
    return stored, restart


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


# Options that describe the body: the built-in scene's, given by a scene file otherwise.
_SCENE_FLAGS = ("mesh", "dim", "refinement", "element", "lam", "mu", "density", "eta_dev", "eta_vol")
_RUN_DEFAULTS = dict(dim=2, refinement=1, integrator="eG", order=1, save_every=1, max_halvings=6, chunk=50,
                     commit_every=5.0, out="jaxvisco-run.h5")


def _scene_file_options(args):
    """Read the scene file of `args` (its path, or the text stored by the run that
    `--resume` continues) and take every run option not given on the command line from
    it; without a scene file fill in the built-in defaults. Returns ``(SceneFile or None,
    the file's schedule as messages name it, or None)``."""
    from .._scenefile._scenefile import read_scene_file

    origin = None
    if args.scene is None and args.scene_source is None:
        for k, v in _RUN_DEFAULTS.items():
            if getattr(args, k) is None:
                setattr(args, k, v)
        return None, origin
    clash = [k for k in _SCENE_FLAGS if getattr(args, k) is not None]
    if clash:
        raise ValueError(f"--{clash[0].replace('_', '-')} cannot be given with a scene file: its [mesh] and "
                         "[material] describe the body (give the overrides in the file).")
    sf = read_scene_file(args.scene, source=args.scene_source, base_dir=args.scene_dir)
    args.scene_source, args.scene_dir = sf.source, sf.base_dir
    if args.schedule is not None and args.t_end is None:
        args.t_end = parse_schedule(args.schedule)[-1][0]  # --schedule without --t-end: to its end
    if sf.rtol is not None and args.rtol is None and args.atol is None and args.schedule is None and args.dt is None:
        args.rtol, args.atol = sf.rtol, sf.atol
        args.dt = sf.dt
    if args.dt is None and args.schedule is None and args.rtol is None and args.atol is None:
        if isinstance(sf.dt, tuple):
            args.schedule = ",".join(f"{a!r}:{b!r}" for a, b in sf.dt)
            origin = f"the schedule of {args.scene} ({args.schedule!r})"
        else:
            args.dt = sf.dt
    file_options = dict(t_end=sf.t_end, integrator=type(sf.integrator).__name__,
                        order=getattr(sf.integrator, "k", 1), max_halvings=sf.max_halvings, out=sf.output["file"],
                        **{k: sf.output[k] for k in ("save_every", "chunk", "commit_every")})
    for k, v in file_options.items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    args.save_gamma = args.save_gamma or sf.output["save_gamma"]
    return sf, origin


def _run(args):
    import jaxvisco as jv

    restart = None
    if args.resume is not None:
        args, restart = _resume_args(args)
    if args.dt is not None and args.schedule is not None:
        raise ValueError("give either --dt or --schedule, not both.")
    if args.schedule is not None and (args.rtol is not None or args.atol is not None):
        raise ValueError("--schedule fixes the steps; --rtol/--atol choose them: give one of the two.")
    sf, schedule_origin = _scene_file_options(args)
    adaptive = args.rtol is not None or args.atol is not None
    if adaptive:
        return _run_adaptive(args, sf, restart)
    integrator, scene = _run_setup(args, sf, restart)
    if args.schedule is not None:
        dt = parse_schedule(args.schedule)
        schedule_name = schedule_origin or f"--schedule {args.schedule!r}"
        t_end = args.t_end if args.t_end is not None else dt[-1][0]
        if t_end > dt[-1][0]:
            if restart is None:
                raise ValueError(f"{schedule_name} ends at t = {dt[-1][0]:g}, before --t-end {t_end:g}: "
                                 f"add a piece that reaches it, e.g. '{args.schedule},{t_end:g}:{dt[-1][1]:g}'.")
            dt[-1] = (math.inf, dt[-1][1])  # --resume --t-end: the last step continues
        try:
            steps = jv.StepTo.from_schedule(0.0, t_end, dt)
        except ValueError as e:
            raise ValueError(f"{schedule_name}: {e}") from None
    else:
        t_end = 1.0 if args.t_end is None else args.t_end
        steps = jv.StepTo.from_schedule(0.0, t_end, 0.1 if args.dt is None else args.dt)
    c = chunk_size([len(steps)], target=args.chunk, save_every=args.save_every)
    state0, v0, ts = None, None, steps.ts
    if restart is not None:
        done = restart.n_steps
        if done >= len(steps) or restart.t >= t_end * (1 - 1e-12):
            raise ValueError(f"{args.resume!r} already reaches t = {restart.t:.6g} (t_end = {t_end:.6g}); "
                             "give a later --t-end to continue it.")
        if not math.isclose(ts[done], restart.t, rel_tol=1e-9, abs_tol=1e-12):
            raise ValueError(f"{args.resume!r}: its {done} steps end at t = {restart.t:.17g}, but the stored schedule "
                             f"puts step {done} at t = {ts[done]:.17g}; it cannot be continued with --t-end {t_end:g}.")
        ts = np.concatenate([[restart.t], ts[done + 1:]])
        state0, v0 = restart.state, restart.velocity
    w = _open_writer(args, sf, scene, integrator, t_end, restart)
    return _write_run(args, integrator, w, lambda stop: run_chunked(
        scene, integrator, jv.StepTo(ts), chunk=c, commit_every=args.commit_every, save_every=args.save_every,
        writer=w, save_gamma=args.save_gamma, label=integrator.name, quiet=args.quiet, initial_state=state0,
        initial_velocity=v0, should_stop=stop, max_halvings=args.max_halvings,
        solver=None if sf is None else sf.solver))


def _write_run(args, integrator, w, go):
    """Run `go(should_stop)` into the open writer `w`, close it with the run's status
    (also when interrupted or failing), and report."""
    status = "failed"
    try:
        with _StopOnSigint(args.quiet) as stop:
            r = go(stop)
        status = r["status"]
    except KeyboardInterrupt:
        status = "interrupted"
        raise
    finally:
        w.close(status=status)
    return _report(args, integrator, status, r)


def _run_setup(args, sf, restart):
    """Check the run options of `args`; the integrator and the scene."""
    if args.mesh is not None and not os.path.isfile(args.mesh):
        raise FileNotFoundError(f"mesh file {args.mesh!r} does not exist.")
    if args.save_every < 1:
        raise ValueError(f"--save-every must be >= 1, got {args.save_every}.")
    if args.chunk < 1:
        raise ValueError(f"--chunk must be >= 1, got {args.chunk}.")
    if not (math.isfinite(args.commit_every) and args.commit_every >= 0):
        raise ValueError(f"--commit-every must be a number of seconds >= 0 (0: every --chunk steps), "
                         f"got {args.commit_every!r}.")
    if not 0 <= args.max_halvings <= 30:
        raise ValueError(f"--max-halvings must be an integer in [0, 30], got {args.max_halvings}.")
    if args.t_end is not None and not math.isfinite(args.t_end):
        raise ValueError(f"--t-end must be a finite time > 0, got {args.t_end!r}.")
    if restart is None and os.path.exists(args.out) and not args.overwrite:
        raise FileExistsError(f"results file {args.out!r} exists; pass --overwrite to replace it, or continue it "
                              f"with --resume {args.out}.")
    integrator = make_integrator(args.integrator, args.order)
    if sf is not None:
        scene = sf.scene
    else:
        scene = make_scene(dim=args.dim, refinement=args.refinement, element=args.element, mesh=args.mesh,
                           lam=args.lam, mu=args.mu, density=args.density, eta_dev=args.eta_dev,
                           eta_vol=args.eta_vol)
    if restart is not None and restart.state.x.shape != scene.x0.shape:
        raise ValueError(f"{args.resume!r}: stored state has shape {restart.state.x.shape}, the scene has "
                         f"{scene.x0.shape}.")
    return integrator, scene


def _open_writer(args, sf, scene, integrator, t_end, restart):
    """The results writer of a run: a new file, or the resumed one appended to."""
    import jaxvisco as jv

    params = {k: v for k, v in vars(args).items() if k != "func"}
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


def _run_adaptive(args, sf, restart):
    """`jaxvisco run` with error-controlled steps (--rtol/--atol)."""
    import jaxvisco as jv

    rtol = args.rtol if args.rtol is not None else args.atol
    atol = args.atol if args.atol is not None else rtol
    try:
        controller = jv.PIDController(rtol=rtol, atol=atol)
    except ValueError as e:
        raise ValueError(f"--rtol/--atol: {e}") from None
    integrator, scene = _run_setup(args, sf, restart)
    t_end = 1.0 if args.t_end is None else args.t_end
    t0, state0, v0, dt0 = 0.0, None, None, args.dt
    if restart is not None:
        if restart.t >= t_end * (1 - 1e-12):
            raise ValueError(f"{args.resume!r} already reaches t = {restart.t:.6g} (t_end = {t_end:.6g}); "
                             "give a later --t-end to continue it.")
        t0, state0, v0 = restart.t, restart.state, restart.velocity
        h = jv.read_results(args.resume)["step_h"]
        dt0 = float(h[-1]) if len(h) else dt0
    w = _open_writer(args, sf, scene, integrator, t_end, restart)
    return _write_run(args, integrator, w, lambda stop: run_adaptive_chunked(
        scene, integrator, controller, t0, t_end, dt0=dt0, chunk=args.chunk, save_every=args.save_every, writer=w,
        save_gamma=args.save_gamma, label=integrator.name, quiet=args.quiet, initial_state=state0,
        initial_velocity=v0, should_stop=stop, solver=None if sf is None else sf.solver))


def momentum_drift(values):
    """`values` (n,) or (n, d) over the frames minus their initial value: ``J(t) - J(0)``."""
    values = np.asarray(values, dtype=float)
    return values - values[:1]


def plot_figure(r, title=""):
    """The `jaxvisco plot` figure of the results dict `r` (`read_results`): H and
    H + dissipated − external work, the energy balance error, and the drift of the linear
    and angular momentum from their initial values (conserved quantities are shown as
    drifts, without axis offset notation, so round-off is not mistaken for motion)."""
    import matplotlib.pyplot as plt

    t, H = r["t"], r["energy"]
    D = r.get("dissipated", np.zeros_like(H))
    W = r.get("external_work", np.zeros_like(H))
    H0 = H[0] if len(H) else 0.0
    worked = bool(np.any(W != 0))
    # The energy scale: |H0| for a free body; a loaded body may start at rest (H0 = 0),
    # so it is the largest energy reached or work done.
    scale = max(float(np.max(np.abs(H), initial=0.0)), float(np.max(np.abs(W), initial=0.0))) or 1.0
    fig, axs = plt.subplots(2, 2, figsize=(11, 7))
    ax = axs[0, 0]
    ax.plot(t, H, label="H")
    if worked:
        ax.plot(t, H + D - W, "--", label="H + dissipated − external work (= H0)")
        ax.plot(t, W, ":", label="external work W (loads, moving supports)")
    else:
        ax.plot(t, H + D, "--", label="H + dissipated (= H0)")
    ax.set_title("energy")
    ax.legend()
    ax = axs[0, 1]
    err = np.abs(H + D - W - H0) / scale
    ax.semilogy(t, np.maximum(err, 1e-17))
    ax.set_title("energy balance error |H + D − W − H0| / max(|H|, |W|)" if worked
                 else "energy balance error |H + D − H0| / max |H|")
    acted = worked or int(r.get("attrs", {}).get("held_components", 0)) > 0
    for ax, key, sym, name in ((axs[1, 0], "linear_momentum", "L", "linear"),
                               (axs[1, 1], "angular_momentum", "J", "angular")):
        ax.set_title(f"{name} momentum {sym} − {sym}(0) (loads, supports act)" if acted
                     else f"{name} momentum drift {sym} − {sym}(0)")
        values = r.get(key)
        if values is None or len(values) == 0:
            continue
        values = np.asarray(values, dtype=float)
        drift = momentum_drift(values)
        if values.ndim == 1:  # 2D angular momentum: J_z
            values, drift, comps = values[:, None], drift[:, None], "z"
        else:
            comps = "xyz"[:values.shape[1]]
        for i, c in enumerate(comps):
            ax.plot(t, drift[:, i], label=f"{sym}_{c} − {sym}_{c}(0),  {sym}_{c}(0) = {values[0, i]:.10g}")
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.legend(fontsize=8)
    for a in axs.flat:
        a.set_xlabel("t")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return fig


def _plot(args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import jaxvisco as jv

    r = jv.read_results(args.results)
    out = args.out or os.path.splitext(args.results)[0] + ".png"
    fig = plot_figure(r, f"{os.path.basename(args.results)}: {r['attrs'].get('integrator', '')} "
                         f"({r['attrs'].get('status', '')})")
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(f"wrote {out}")
    return 0


def build_parser():
    p = argparse.ArgumentParser(prog="jaxvisco", description="Finite-strain viscoelastodynamics with "
                                "energy-consistent Galerkin time elements (Gross & Betsch 2005).")
    p.add_argument("--version", action="version", version=f"jaxvisco {_version()}")
    sub = p.add_subparsers(dest="command", metavar="{paper,run,plot,scene-template}")
    sub.required = True

    q = sub.add_parser("paper", help="cG(1) vs eG(1) on the paper's L-shape; energy.png + results files",
                       description="Run cG(1) and eG(1) on the 2D L-shape (refinement 1) with h = 0.1 up to t = 20 "
                       "then h = 1.0, and with h = 1.0 from the outset; write one results file per run and "
                       "energy.png.")
    q.add_argument("--quick", action="store_true", help=f"short version: stop at t = {QUICK_T:g}")
    q.add_argument("--t-end", type=float, default=None, help=f"final time (default {PAPER_T:g}, {QUICK_T:g} with --quick)")
    q.add_argument("--out", default="paper-out", help="output directory (default: paper-out)")
    q.add_argument("--quiet", action="store_true", help="no progress lines")
    q.add_argument("--overwrite", action="store_true", help="replace existing results files in --out")
    q.set_defaults(func=_paper)

    r = sub.add_parser("run", help="integrate a scene file, a built-in L-shape or a mesh file",
                       description="Integrate the scene of a scene file (SCENE.toml: mesh, groups, material, initial "
                       "velocity, clamps, loads, tractions, integrator, steps, output; `jaxvisco scene-template` "
                       "prints a commented one), or the paper's L-shape (or a mesh file with the paper's material and "
                       "rigid initial velocity), with any integrator; write an HDF5 results file and XDMF. With a "
                       "scene file the options --integrator, --order, --t-end, --dt, --schedule, --save-every, "
                       "--save-gamma, --max-halvings, --chunk, --commit-every and --out override the file's; the "
                       "body's options (--mesh, --dim, --refinement, --element, --lam, --mu, --density, --eta-*) "
                       "are refused.")
    r.add_argument("scene", nargs="?", default=None, metavar="SCENE.toml",
                   help="a scene file (default: the built-in L-shape, or --mesh)")
    r.add_argument("--dim", type=int, default=None, help="2 or 3 (built-in L-shape; default 2)")
    r.add_argument("--refinement", type=int, default=None, help="elements per unit length (default 1)")
    r.add_argument("--element", default=None, help="cell type, e.g. quad4, quad9, tri3, hex8, tet10 (default quad4/hex8)")
    r.add_argument("--mesh", default=None, help="a mesh file (any meshio format) instead of the built-in L-shape")
    r.add_argument("--integrator", default=None, help="cG, eG, Newmark or Midpoint (default eG)")
    r.add_argument("--order", type=int, default=None, help="polynomial degree k of cG(k)/eG(k) (default 1)")
    r.add_argument("--t-end", type=float, default=None, help="final time (default 1, or the schedule's last time)")
    r.add_argument("--dt", type=float, default=None, help="constant time step (default 0.1)")
    r.add_argument("--schedule", default=None, help="piecewise-constant steps 'T1:DT1,T2:DT2', e.g. '20:0.1,40:1.0'")
    r.add_argument("--rtol", type=float, default=None,
                   help="error-controlled steps with this relative tolerance (jaxvisco.PIDController; --atol "
                   "defaults to it); --dt is then the first step tried")
    r.add_argument("--atol", type=float, default=None, help="absolute tolerance of error-controlled steps "
                   "(default: --rtol)")
    for name in ("eta-dev", "eta-vol", "lam", "mu", "density"):
        r.add_argument("--" + name, type=float, default=None, help=f"material parameter {name} (default: paper)")
    r.add_argument("--save-every", type=int, default=None, help="save every N-th step (default 1)")
    r.add_argument("--save-gamma", action="store_true", help="also store the internal variable /qp/gamma")
    r.add_argument("--max-halvings", type=int, default=None,
                   help="a failed step is halved at most N times (smallest step h/2**N) before the run stops "
                   "(default 6)")
    r.add_argument("--chunk", type=int, default=None, help="at most N steps per compiled call (default 50)")
    r.add_argument("--commit-every", type=float, default=None, metavar="SECONDS",
                   help="commit the results at least about every SECONDS of computing (chunks sized from the "
                   "measured time per step; default 5); 0: commit every --chunk steps, so that a run split at a "
                   "commit repeats the uninterrupted one exactly")
    r.add_argument("--overwrite", action="store_true", help="replace an existing results file")
    r.add_argument("--out", default=None, help="results file (default jaxvisco-run.h5, or the scene file's [output] "
                   "file); an .xdmf goes beside it")
    r.add_argument("--quiet", action="store_true", help="no progress lines")
    r.add_argument("--resume", default=None, metavar="RESULTS.h5",
                   help="continue the run stored in RESULTS.h5 (appending to it) with its own options; "
                   "--t-end extends it (a --schedule's last step continues); a run of a scene file is rebuilt from "
                   "the copy of the file stored in RESULTS.h5")
    r.set_defaults(func=_run, scene_source=None, scene_dir=None)

    st = sub.add_parser("scene-template", help="print a commented scene file",
                        description="Print a commented scene file that documents every key and runs as it stands "
                        "(a clamped strip under a tip load switched off at t = 1): jaxvisco scene-template > "
                        "my.toml; jaxvisco run my.toml")
    st.set_defaults(func=_scene_template)

    pl = sub.add_parser("plot", help="plot energy, energy balance and momenta from a results file",
                        description="Plot H, H + dissipated, the energy balance error and the momenta of a results file.")
    pl.add_argument("results", help="a results .h5 file")
    pl.add_argument("--out", default=None, help="PNG file (default: beside the results file)")
    pl.set_defaults(func=_plot)
    return p


def _scene_template(args):
    from .._scenefile._scenetemplate import TEMPLATE

    sys.stdout.write(TEMPLATE)
    return 0


def _version():
    from jaxvisco import __version__

    return __version__


def main(argv=None):
    """Entry point of the ``jaxvisco`` console script; returns the exit code."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxvisco as jv

    args = build_parser().parse_args(argv)
    try:
        jv.enable_compilation_cache()  # JAXVISCO_CACHE_DIR=DIR elsewhere, =off to disable
    except OSError as e:
        print(f"jaxvisco: warning: no compilation cache ({e}); every run compiles afresh", file=sys.stderr)
    try:
        return args.func(args)
    except (ValueError, TypeError, FileNotFoundError, OSError, jv.SolverError, _CLIError) as e:
        msg = " ".join(str(e).split())
        print(f"jaxvisco: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxvisco: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
