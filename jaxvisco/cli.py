"""Command line: ``jaxvisco paper | run | plot``.

``jaxvisco paper`` reproduces the L-shape comparison of Groß & Betsch (2005) (cG(1)
against eG(1), a step-size change at t = 20 and large steps from the outset), ``jaxvisco
run`` integrates a built-in L-shape or a mesh file with any integrator, ``jaxvisco plot``
draws energy, energy balance and momenta from a results file. Every subcommand has
``--help``. Runs are advanced in equal-sized chunks (one compiled program reused) so that
progress can be printed and the results file grows as the run goes.
"""

import argparse
import inspect
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


def _pieces(t_start, hs):
    """A dt schedule that `simulate` turns back into exactly the steps `hs`."""
    out, t = [], t_start
    i = 0
    while i < len(hs):
        j = i
        while j + 1 < len(hs) and hs[j + 1] == hs[i]:
            j += 1
        t = t + float(np.sum(hs[i:j + 1]))
        out.append((t, float(hs[i]) * (1 + 1e-12)))
        i = j + 1
    return out, t


def run_chunked(scene, integrator, hs, t0=0.0, chunk=50, save_every=1, solver=None, writer=None,
                save_gamma=False, label="", quiet=False, stream=None, initial_state=None, initial_velocity=None,
                should_stop=None, max_halvings=6):
    """Integrate over the steps `hs` in chunks of `chunk` steps, appending to `writer`.

    Each chunk starts from the previous chunk's last state and predictor velocity, so
    the chunks continue one run; `initial_state`/`initial_velocity` continue a saved run
    (a restart: its first frame is not written again). `should_stop()` is asked after
    every chunk; when true the run ends with status "interrupted".

    Returns a dict: `t`, `energy` (all saved frames), `status`, `steps`, `wall`,
    `newton` (total iterations), `state` (last state).
    """
    import jax.numpy as jnp

    import jaxvisco as jv

    stream = stream or sys.stderr
    solver = solver or jv.NewtonKrylov()
    hs = np.asarray(hs, dtype=float)
    n = len(hs)
    state, t, v = initial_state, float(t0), initial_velocity
    resumed = initial_state is not None
    ts, Hs = [], []
    status, done, newton = "done", 0, 0
    start = time.perf_counter()
    if not quiet:
        print(f"{label}: {n} steps in chunks of {chunk} (the first chunk compiles, ~30-60 s)", file=stream, flush=True)
    extra = {}
    if "max_steps" in inspect.signature(jv.simulate).parameters:
        extra["max_steps"] = chunk  # a shorter last chunk reuses the compiled program
    for i0 in range(0, n, chunk):
        h = hs[i0:i0 + chunk]
        dt, t_end = _pieces(t, h)
        sol = jv.simulate(scene, integrator, t_end=t_end, dt=dt, t0=t, save_every=save_every, solver=solver,
                          save_gamma=True, initial_state=state, throw=False, initial_velocity=v,
                          max_halvings=max_halvings, **extra)
        first = state is None
        if writer is not None:
            writer.append(sol, skip_first=not first, gamma=save_gamma)
        s = 0 if (first or (resumed and not ts)) else 1
        ts.extend(np.asarray(sol.t)[s:].tolist())
        Hs.extend(np.asarray(sol.energy)[s:].tolist())
        ns = int(len(np.asarray(sol.step_t)))
        done += ns
        its = np.asarray(sol.newton_iterations)
        newton += int(its.sum())
        state = sol.state(-1)
        v = sol.end_velocity
        t = float(np.asarray(sol.t)[-1])
        if not quiet:
            print(f"{label}: t = {t:9.4f}  step {done:6d}/{n}  newton/step {its.mean() if ns else 0:4.1f}"
                  f"  H = {Hs[-1]:.8g}", file=stream, flush=True)
        if sol.status == "failed":
            status = "failed"
            break
        if sol.status == "equilibrium":
            status = "equilibrium"
            break
        if should_stop is not None and should_stop() and i0 + chunk < n:
            status = "interrupted"
            break
    state = jv.State(jnp.asarray(state.x), jnp.asarray(state.p), state.gamma)
    return dict(t=np.asarray(ts), energy=np.asarray(Hs), status=status, steps=done, newton=newton,
                wall=time.perf_counter() - start, state=state, t_last=t)


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
    from jaxvisco.scenes._lshape import PAPER

    p = dict(PAPER)
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
    from jaxvisco._results import ResultsWriter, scene_attributes
    from jaxvisco._schedule import step_sizes

    out = args.out
    os.makedirs(out, exist_ok=True)
    if args.quick:
        T = QUICK_T if args.t_end is None else args.t_end
    else:
        T = PAPER_T if args.t_end is None else args.t_end
    # h = 0.2 is already too large for cG(1) before t = 20 (its energy grows ~9x by
    # t = 19); h = 0.1 keeps it bounded there, and running it costs little beside
    # compilation, so --quick only shortens the final time.
    schedule = [(20.0, 0.1), (T, 1.0)]
    scene = jv.scenes.lshape(dim=2, refinement=1)
    runs = [("schedule", step_sizes(0.0, T, schedule)), ("large", step_sizes(0.0, T, 1.0))]
    c = chunk_size([len(h) for _, h in runs], target=50)
    results = []
    for scheme_name, integrator in (("cG1", jv.cG(1)), ("eG1", jv.eG(1))):
        for sched_name, hs in runs:
            label = f"{scheme_name}_{sched_name}"
            path = os.path.join(out, label + ".h5")
            attrs = dict(scene_attributes(scene), scene="lshape", refinement=1, integrator=integrator.describe(),
                         parameters=dict(schedule=schedule if sched_name == "schedule" else [(T, 1.0)], t_end=T))
            w = ResultsWriter(path, scene.mesh, attrs)
            status = "failed"
            try:
                r = run_chunked(scene, integrator, hs, chunk=c, writer=w, label=label, quiet=args.quiet)
                status = r["status"]
            except KeyboardInterrupt:
                status = "interrupted"
                raise
            finally:
                w.close(status=status)
            results.append((scheme_name, sched_name, r))
            sched_txt = "h=0.1->1.0@t=20" if sched_name == "schedule" else "h=1.0"
            print(f"{scheme_name:4s} {sched_txt:16s} status={r['status']:11s} H0={r['energy'][0]:.6g} "
                  f"H_end={r['energy'][-1]:.6g} (t={r['t_last']:.4g}) steps={r['steps']} wall={r['wall']:.1f}s",
                  flush=True)
            _warn_energy(path, label)
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


def _warn_energy(path, label):
    """Print `energy_warning` for the results file `path` to stderr, if it warns."""
    from jaxvisco._results import read_results

    r = read_results(path)
    H = r["energy"]
    msg = energy_warning(r["t"], H, r.get("dissipated", np.zeros_like(H)), r.get("external_work", np.zeros_like(H)),
                         label)
    if msg is not None:
        print(f"jaxvisco: warning: {msg}", file=sys.stderr, flush=True)


_RESUMABLE = ("t_end", "quiet", "resume")


def _resume_args(args):
    """The options of the run stored in `args.resume`, with `--t-end` and `--quiet`
    taken from the command line."""
    from jaxvisco._results import read_restart

    restart = read_restart(args.resume)
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


def _run(args):
    import jaxvisco as jv
    from jaxvisco._results import ResultsWriter, scene_attributes
    from jaxvisco._schedule import step_sizes

    restart = None
    if args.resume is not None:
        args, restart = _resume_args(args)
    if args.dt is not None and args.schedule is not None:
        raise ValueError("give either --dt or --schedule, not both.")
    if args.mesh is not None and not os.path.isfile(args.mesh):
        raise FileNotFoundError(f"mesh file {args.mesh!r} does not exist.")
    if args.save_every < 1:
        raise ValueError(f"--save-every must be >= 1, got {args.save_every}.")
    if args.chunk < 1:
        raise ValueError(f"--chunk must be >= 1, got {args.chunk}.")
    if not 0 <= args.max_halvings <= 30:
        raise ValueError(f"--max-halvings must be an integer in [0, 30], got {args.max_halvings}.")
    if args.t_end is not None and not math.isfinite(args.t_end):
        raise ValueError(f"--t-end must be a finite time > 0, got {args.t_end!r}.")
    integrator = make_integrator(args.integrator, args.order)
    scene = make_scene(dim=args.dim, refinement=args.refinement, element=args.element, mesh=args.mesh,
                       lam=args.lam, mu=args.mu, density=args.density, eta_dev=args.eta_dev, eta_vol=args.eta_vol)
    if args.schedule is not None:
        dt = parse_schedule(args.schedule)
        t_end = args.t_end if args.t_end is not None else dt[-1][0]
    else:
        dt = 0.1 if args.dt is None else args.dt
        t_end = 1.0 if args.t_end is None else args.t_end
    hs = step_sizes(0.0, t_end, dt)
    c = chunk_size([len(hs)], target=args.chunk, save_every=args.save_every)
    t0, state0, v0 = 0.0, None, None
    if restart is not None:
        done = restart.n_steps
        t_done = float(np.sum(hs[:done]))
        if done >= len(hs) or restart.t >= t_end * (1 - 1e-12):
            raise ValueError(f"{args.resume!r} already reaches t = {restart.t:.6g} (t_end = {t_end:.6g}); "
                             "give a later --t-end to continue it.")
        if not math.isclose(t_done, restart.t, rel_tol=1e-9, abs_tol=1e-12):
            raise ValueError(f"{args.resume!r}: its {done} steps end at t = {restart.t:.17g}, but the stored schedule "
                             f"puts step {done} at t = {t_done:.17g}; it cannot be continued with --t-end {t_end:g}.")
        if restart.state.x.shape != scene.initial_state().x.shape:
            raise ValueError(f"{args.resume!r}: stored state has shape {restart.state.x.shape}, the scene has "
                             f"{scene.initial_state().x.shape}.")
        hs, t0, state0, v0 = hs[done:], restart.t, restart.state, restart.velocity
    params = {k: v for k, v in vars(args).items() if k != "func"}
    params["t_end"] = t_end
    attrs = dict(scene_attributes(scene), scene=("mesh:" + args.mesh) if args.mesh else "lshape",
                 integrator=integrator.describe(), parameters=params)
    if restart is not None:
        w = ResultsWriter(args.out, append=True, attrs={"parameters": params})
    else:
        w = ResultsWriter(args.out, scene.mesh, attrs)
    status = "failed"
    try:
        with _StopOnSigint(args.quiet) as stop:
            r = run_chunked(scene, integrator, hs, t0=t0, chunk=c, save_every=args.save_every, writer=w,
                            save_gamma=args.save_gamma, label=integrator.name, quiet=args.quiet,
                            initial_state=state0, initial_velocity=v0, should_stop=stop,
                            max_halvings=args.max_halvings)
        status = r["status"]
    except KeyboardInterrupt:
        status = "interrupted"
        raise
    finally:
        w.close(status=status)
    print(f"{integrator.name}: status={status} H0={r['energy'][0]:.8g} H_end={r['energy'][-1]:.8g} "
          f"t={r['t_last']:.6g} steps={r['steps']} wall={r['wall']:.1f}s -> {args.out}", flush=True)
    if status == "failed":
        raise jv.SolverError(f"{integrator.name}: the step after t = {r['t_last']:.6g} did not converge; "
                             f"results up to it are in {args.out}", r["t_last"], r["state"], None)
    if status == "interrupted":
        print(f"jaxvisco: interrupted at t = {r['t_last']:.6g}; continue with: jaxvisco run --resume {args.out}",
              file=sys.stderr, flush=True)
        return 130
    return 0


def momentum_drift(values):
    """`values` (n,) or (n, d) over the frames minus their initial value: ``J(t) - J(0)``."""
    values = np.asarray(values, dtype=float)
    return values - values[:1]


def plot_figure(r, title=""):
    """The `jaxvisco plot` figure of the results dict `r` (`read_results`): H and H +
    dissipated, the energy balance error, and the drift of the linear and angular
    momentum from their initial values (conserved quantities are shown as drifts, without
    axis offset notation, so round-off is not mistaken for motion)."""
    import matplotlib.pyplot as plt

    t, H = r["t"], r["energy"]
    D = r.get("dissipated", np.zeros_like(H))
    H0 = H[0] if len(H) else 1.0
    fig, axs = plt.subplots(2, 2, figsize=(11, 7))
    ax = axs[0, 0]
    ax.plot(t, H, label="H")
    ax.plot(t, H + D, "--", label="H + dissipated (= H0)")
    ax.set_title("energy")
    ax.legend()
    ax = axs[0, 1]
    err = np.abs(H - H0 + D) / abs(H0)
    ax.semilogy(t, np.maximum(err, 1e-17))
    ax.set_title("energy balance error |H - H0 + D| / H0")
    for ax, key, sym, name in ((axs[1, 0], "linear_momentum", "L", "linear"),
                               (axs[1, 1], "angular_momentum", "J", "angular")):
        ax.set_title(f"{name} momentum drift {sym} − {sym}(0)")
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

    from jaxvisco._results import read_results

    r = read_results(args.results)
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
    sub = p.add_subparsers(dest="command", metavar="{paper,run,plot}")
    sub.required = True

    q = sub.add_parser("paper", help="cG(1) vs eG(1) on the paper's L-shape; energy.png + results files",
                       description="Run cG(1) and eG(1) on the 2D L-shape (refinement 1) with h = 0.1 up to t = 20 "
                       "then h = 1.0, and with h = 1.0 from the outset; write one results file per run and "
                       "energy.png.")
    q.add_argument("--quick", action="store_true", help=f"short version: stop at t = {QUICK_T:g}")
    q.add_argument("--t-end", type=float, default=None, help=f"final time (default {PAPER_T:g}, {QUICK_T:g} with --quick)")
    q.add_argument("--out", default="paper-out", help="output directory (default: paper-out)")
    q.add_argument("--quiet", action="store_true", help="no progress lines")
    q.set_defaults(func=_paper)

    r = sub.add_parser("run", help="integrate a built-in L-shape or a mesh file",
                       description="Integrate the paper's L-shape (or a mesh file with the paper's material and "
                       "rigid initial velocity) with any integrator; write an HDF5 results file and XDMF.")
    r.add_argument("--dim", type=int, default=2, help="2 or 3 (built-in L-shape; default 2)")
    r.add_argument("--refinement", type=int, default=1, help="elements per unit length (default 1)")
    r.add_argument("--element", default=None, help="cell type, e.g. quad4, quad9, tri3, hex8, tet10 (default quad4/hex8)")
    r.add_argument("--mesh", default=None, help="a mesh file (any meshio format) instead of the built-in L-shape")
    r.add_argument("--integrator", default="eG", help="cG, eG, Newmark or Midpoint (default eG)")
    r.add_argument("--order", type=int, default=1, help="polynomial degree k of cG(k)/eG(k) (default 1)")
    r.add_argument("--t-end", type=float, default=None, help="final time (default 1, or the schedule's last time)")
    r.add_argument("--dt", type=float, default=None, help="constant time step (default 0.1)")
    r.add_argument("--schedule", default=None, help="piecewise-constant steps 'T1:DT1,T2:DT2', e.g. '20:0.1,40:1.0'")
    for name in ("eta-dev", "eta-vol", "lam", "mu", "density"):
        r.add_argument("--" + name, type=float, default=None, help=f"material parameter {name} (default: paper)")
    r.add_argument("--save-every", type=int, default=1, help="save every N-th step (default 1)")
    r.add_argument("--save-gamma", action="store_true", help="also store the internal variable /qp/gamma")
    r.add_argument("--max-halvings", type=int, default=6,
                   help="a failed step is halved at most N times (smallest step h/2**N) before the run stops "
                   "(default 6)")
    r.add_argument("--chunk", type=int, default=50, help="steps per compiled chunk (progress granularity; default 50)")
    r.add_argument("--out", default="jaxvisco-run.h5", help="results file (default jaxvisco-run.h5); an .xdmf goes beside it")
    r.add_argument("--quiet", action="store_true", help="no progress lines")
    r.add_argument("--resume", default=None, metavar="RESULTS.h5",
                   help="continue the run stored in RESULTS.h5 (appending to it) with its own options; "
                   "--t-end extends it")
    r.set_defaults(func=_run)

    pl = sub.add_parser("plot", help="plot energy, energy balance and momenta from a results file",
                        description="Plot H, H + dissipated, the energy balance error and the momenta of a results file.")
    pl.add_argument("results", help="a results .h5 file")
    pl.add_argument("--out", default=None, help="PNG file (default: beside the results file)")
    pl.set_defaults(func=_plot)
    return p


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
