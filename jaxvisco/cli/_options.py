"""The options of ``jaxvisco run``: those of a resumed run read back from its results
file (`_resume_args`), those a scene file supplies where the command line gives none or
the built-in defaults (`_scene_file_options`), and their checks together with the
integrator and scene they build (`_run_setup`).
"""

import argparse
import math
import os

from ._setup import make_integrator, make_scene, parse_schedule

_RESUMABLE = ("t_end", "quiet", "resume")
# Bookkeeping of the parser, not options of the run (never stored, never compared).
_BOOKKEEPING = ("func", "deprecated", "spelled")
# The option strings of the dests whose names differ from them.
_FLAGS = dict(t_end="--t1", dt="--dt0", element="--cell-type")


def flag(args, dest):
    """The option that sets `dest`, as the command line wrote it (a deprecated spelling
    such as ``--t-end`` where it was used) for messages that name it."""
    spelled = getattr(args, "spelled", None) or {}
    return spelled.get(dest) or _FLAGS.get(dest, "--" + dest.replace("_", "-"))


def t1_name(args):
    """What messages about the end time call it: ``t_end`` if ``--t-end`` was written."""
    return "t_end" if flag(args, "t_end") == "--t-end" else "t1"


def _resume_args(args):
    """The options of the run stored in `args.resume`, with `--t1` and `--quiet`
    taken from the command line."""
    import jaxvisco as jv

    from ._main import build_parser

    restart = jv.read_restart(args.resume)
    if args.scene is not None:
        raise ValueError(f"with --resume the scene comes from the results file; give no scene file "
                         f"({args.scene!r}), only {flag(args, 't_end')} and --quiet.")
    given = {k: v for k, v in vars(args).items() if k not in _BOOKKEEPING + _RESUMABLE}
    defaults = {k: v for k, v in vars(build_parser().parse_args(["run"])).items() if k in given}
    changed = sorted(k for k, v in given.items() if v != defaults[k])
    if changed:
        raise ValueError(f"with --resume the run's options come from the results file; only --t1 and --quiet "
                         f"may be given, got {', '.join(flag(args, c) for c in changed)}.")
    params = restart.attrs.get("parameters")
    if not isinstance(params, dict) or "integrator" not in params:
        raise ValueError(f"{args.resume!r} was not written by `jaxvisco run` (no run parameters stored); "
                         "continue it from Python with jaxvisco.resume.")
    stored = argparse.Namespace(**{**defaults, **{k: v for k, v in params.items() if k in defaults}})
    stored.t_end = params.get("t_end") if args.t_end is None else args.t_end
    stored.quiet, stored.out, stored.resume = args.quiet, args.resume, args.resume
    stored.func, stored.deprecated, stored.spelled = args.func, args.deprecated, args.spelled
    return stored, restart


# Options that describe the body: the built-in scene's, given by a scene file otherwise.
_SCENE_FLAGS = ("mesh", "dim", "refinement", "element", "lam", "mu", "density", "eta_dev", "eta_vol", "velocity",
                "angular_velocity")


_RUN_DEFAULTS = dict(t0=0.0, dim=2, refinement=1, integrator="eG", order=1, save_every=1, max_halvings=6, chunk=50,
                     commit_every=5.0, out="jaxvisco-run.h5")


def _scene_file_options(args):
    """Read the scene file of `args` (its path, or the text stored by the run that
    `--resume` continues) and take every run option not given on the command line from
    it; without a scene file fill in the built-in defaults. Returns ``(SceneFile or None,
    the file's schedule as messages name it, or None)``."""
    from .._scenefile._scenefile import read_quietly

    origin = None
    if args.scene is None and args.scene_source is None:
        for k, v in _RUN_DEFAULTS.items():
            if getattr(args, k) is None:
                setattr(args, k, v)
        return None, origin
    clash = [k for k in _SCENE_FLAGS if getattr(args, k) is not None]
    if clash:
        raise ValueError(f"{flag(args, clash[0])} cannot be given with a scene file: its [mesh], [material] and "
                         "[initial] describe the body (give the overrides in the file).")
    sf = read_quietly(args.scene, source=args.scene_source, base_dir=args.scene_dir)
    args.scene_source, args.scene_dir = sf.source, sf.base_dir
    if sf.deprecated and args.resume is None:  # a resumed run's file was noted when it started
        args.deprecated = list(args.deprecated or []) + list(sf.deprecated)
    if args.schedule is not None and args.t_end is None:
        args.t_end = parse_schedule(args.schedule)[-1][0]  # --schedule without --t1: to its end
    if sf.rtol is not None and args.rtol is None and args.atol is None and args.schedule is None and args.dt is None:
        args.rtol, args.atol = sf.rtol, sf.atol
        args.dt = sf.dt0
    if args.dt is None and args.schedule is None and args.rtol is None and args.atol is None:
        if isinstance(sf.dt0, tuple):
            args.schedule = ",".join(f"{a!r}:{b!r}" for a, b in sf.dt0)
            origin = f"the schedule of {args.scene} ({args.schedule!r})"
        else:
            args.dt = sf.dt0
    file_options = dict(t0=sf.t0, t_end=sf.t1, integrator=type(sf.integrator).__name__,
                        order=getattr(sf.integrator, "k", 1), max_halvings=sf.max_halvings, out=sf.output["file"],
                        save_every=sf.saveat.every, **{k: sf.output[k] for k in ("chunk", "commit_every")})
    for k, v in file_options.items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    args.save_gamma = args.save_gamma or sf.saveat.gamma
    return sf, origin


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
        raise ValueError(f"{flag(args, 't_end')} must be a finite time > 0, got {args.t_end!r}.")
    if not math.isfinite(args.t0):
        raise ValueError(f"--t0 must be a finite time, got {args.t0!r}.")
    if restart is None and os.path.exists(args.out) and not args.overwrite:
        raise FileExistsError(f"results file {args.out!r} exists; pass --overwrite to replace it, or continue it "
                              f"with --resume {args.out}.")
    integrator = make_integrator(args.integrator, args.order)
    if sf is not None and type(integrator) is type(sf.integrator) and getattr(integrator, "k", 1) == \
            getattr(sf.integrator, "k", 1):
        integrator = sf.integrator  # the file's, with its [integrator] quadrature
    if sf is not None:
        scene = sf.scene
    else:
        scene = make_scene(dim=args.dim, refinement=args.refinement, cell_type=args.element, mesh=args.mesh,
                           lam=args.lam, mu=args.mu, density=args.density, eta_dev=args.eta_dev,
                           eta_vol=args.eta_vol, velocity=args.velocity, angular_velocity=args.angular_velocity)
    if restart is not None and restart.state.x.shape != scene.x0.shape:
        raise ValueError(f"{args.resume!r}: stored state has shape {restart.state.x.shape}, the scene has "
                         f"{scene.x0.shape}.")
    return integrator, scene
