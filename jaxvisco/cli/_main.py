"""Command line: ``jaxvisco paper | run | identify | plot | scene-template``.

``jaxvisco paper`` reproduces the L-shape comparison of Groß & Betsch (2005) (cG(1)
against eG(1), a step-size change at t = 20 and large steps from the outset), ``jaxvisco
run`` integrates a scene file (``jaxvisco run SCENE.toml``, see `_scenefile`), a built-in
L-shape or a mesh file with any integrator, ``jaxvisco plot`` draws energy, energy
balance and momenta from a results file, ``jaxvisco scene-template`` prints a commented
scene file. Every subcommand has ``--help``. Runs are advanced in equal-sized chunks (one
compiled program reused) so that progress can be printed and the results file grows as
the run goes.

This module holds the parser (`build_parser`) and the entry point (`main`); the
subcommands are in `_paper`, `_run` (with `_options`), `_plot`, and what they share in
`_chunked`, `_setup` and `_checks`. The names tests and scripts import from here are
re-exported.
"""

import argparse
import sys
import warnings

from ._checks import energy_warning as energy_warning
from ._chunked import chunk_size as chunk_size
from ._chunked import run_adaptive_chunked as run_adaptive_chunked
from ._chunked import run_chunked as run_chunked
from ._identify import _identify
from ._options import _scene_file_options as _scene_file_options
from ._paper import PAPER_T, QUICK_T, _paper
from ._plot import _plot
from ._plot import momentum_drift as momentum_drift
from ._plot import plot_figure as plot_figure
from ._run import _run
from ._setup import make_integrator as make_integrator
from ._setup import make_scene as make_scene
from ._setup import parse_schedule as parse_schedule


def build_parser():
    p = argparse.ArgumentParser(prog="jaxvisco", description="Finite-strain viscoelastodynamics with "
                                "energy-consistent Galerkin time elements (Gross & Betsch 2005).")
    p.add_argument("--version", action="version", version=f"jaxvisco {_version()}")
    sub = p.add_subparsers(dest="command", metavar="{paper,run,identify,plot,scene-template}")
    sub.required = True

    q = sub.add_parser("paper", help="cG(1) vs eG(1) on the paper's L-shape; energy.png + results files",
                       description="Run cG(1) and eG(1) on the 2D L-shape (refinement 1) with h = 0.1 up to t = 20 "
                       "then h = 1.0, and with h = 1.0 from the outset; write one results file per run and "
                       "energy.png.")
    q.add_argument("--quick", action="store_true", help=f"short version: stop at t = {QUICK_T:g}")
    q.add_argument("--t1", dest="t_end", type=float, default=None,
                   help=f"final time (default {PAPER_T:g}, {QUICK_T:g} with --quick)")
    q.add_argument("--t-end", dest="t_end", type=float, action=_Deprecated, new="--t1", help=argparse.SUPPRESS)
    q.add_argument("--out", default="paper-out", help="output directory (default: paper-out)")
    q.add_argument("--quiet", action="store_true", help="no progress lines")
    q.add_argument("--overwrite", action="store_true", help="replace existing results files in --out")
    q.set_defaults(func=_paper, deprecated=None, spelled=None)

    r = sub.add_parser("run", help="integrate a scene file, a built-in L-shape or a mesh file",
                       description="Integrate the scene of a scene file (SCENE.toml: mesh, groups, material, initial "
                       "velocity, clamps, loads, tractions, integrator, steps, output; `jaxvisco scene-template` "
                       "prints a commented one), or the paper's L-shape, or a mesh file with the material and "
                       "initial velocity given here (at rest by default), with any integrator; write an HDF5 results "
                       "file and XDMF. With a scene file the options --integrator, --order, --t0, --t1, --dt0, "
                       "--schedule, --rtol, --atol, --save-every, --save-gamma, --max-halvings, --chunk, "
                       "--commit-every and --out override the file's; the body's options (--mesh, --dim, "
                       "--refinement, --cell-type, --lam, --mu, --density, --eta-*, --velocity, --angular-velocity) "
                       "are refused. --t-end, --dt and --element are deprecated spellings of --t1, --dt0 and "
                       "--cell-type.")
    r.add_argument("scene", nargs="?", default=None, metavar="SCENE.toml",
                   help="a scene file (default: the built-in L-shape, or --mesh)")
    r.add_argument("--dim", type=int, default=None, help="2 or 3 (built-in L-shape; default 2)")
    r.add_argument("--refinement", type=int, default=None, help="elements per unit length (default 1)")
    r.add_argument("--cell-type", dest="element", default=None,
                   help="cell type of the built-in L-shape, e.g. quad4, quad9, tri3, hex8, tet10 (default quad4/hex8)")
    r.add_argument("--element", dest="element", action=_Deprecated, new="--cell-type", help=argparse.SUPPRESS)
    r.add_argument("--mesh", default=None, help="a mesh file (any meshio format) instead of the built-in L-shape; "
                   "give its material (--lam, --mu, --density; --eta-dev/--eta-vol for a viscous body) and, if it "
                   "is to move, --velocity/--angular-velocity (default: at rest)")
    r.add_argument("--velocity", default=None, metavar="VX,VY[,VZ]",
                   help="with --mesh: initial rigid translation (default 0)")
    r.add_argument("--angular-velocity", default=None, metavar="W | WX,WY,WZ",
                   help="with --mesh: initial rigid rotation about the origin, a number in 2D, a vector in 3D "
                   "(default 0)")
    r.add_argument("--integrator", default=None, help="cG, eG, Newmark or Midpoint (default eG)")
    r.add_argument("--order", type=int, default=None, help="polynomial degree k of cG(k)/eG(k) (default 1)")
    r.add_argument("--t0", type=float, default=None, help="start time (default 0)")
    r.add_argument("--t1", dest="t_end", type=float, default=None,
                   help="end time (default 1, or the schedule's last time)")
    r.add_argument("--t-end", dest="t_end", type=float, action=_Deprecated, new="--t1", help=argparse.SUPPRESS)
    r.add_argument("--dt0", dest="dt", type=float, default=None, help="constant time step (default 0.1)")
    r.add_argument("--dt", dest="dt", type=float, action=_Deprecated, new="--dt0", help=argparse.SUPPRESS)
    r.add_argument("--schedule", default=None, help="piecewise-constant steps 'T1:DT1,T2:DT2', e.g. '20:0.1,40:1.0'")
    r.add_argument("--rtol", type=float, default=None,
                   help="error-controlled steps with this relative tolerance (jaxvisco.PIDController; --atol "
                   "defaults to it); --dt0 is then the first step tried")
    r.add_argument("--atol", type=float, default=None, help="absolute tolerance of error-controlled steps "
                   "(default: --rtol)")
    for name in ("eta-dev", "eta-vol", "lam", "mu", "density"):
        r.add_argument("--" + name, type=float, default=None,
                       help=f"material parameter {name} (built-in L-shape: default the paper's; --mesh: "
                       f"{'default inf, elastic' if name.startswith('eta') else 'required'})")
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
                   "--t1 extends it (a --schedule's last step continues); a run of a scene file is rebuilt from "
                   "the copy of the file stored in RESULTS.h5")
    r.set_defaults(func=_run, scene_source=None, scene_dir=None, deprecated=None, spelled=None)

    st = sub.add_parser("scene-template", help="print a commented scene file",
                        description="Print a commented scene file that documents every key and runs as it stands "
                        "(a clamped strip under a tip load switched off at t = 1): jaxvisco scene-template > "
                        "my.toml; jaxvisco run my.toml")
    st.set_defaults(func=_scene_template)

    fi = sub.add_parser("identify", help="fit material parameters to experiments (scene files + CSV data)",
                        description="Fit material parameters to one or several experiments, each a scene file with "
                        "measured data in a CSV file (the supports' forces, marker displacements, extensometers); "
                        "print each value with its confidence interval, write a JSON report and a plot of the fit. "
                        "The fit file's format: the user guide's page \"Identification from experiments\".")
    fi.add_argument("fit", metavar="FIT.toml", help="the fit file")
    fi.add_argument("--report", default=None, help="JSON report (default: beside the fit file)")
    fi.add_argument("--plot", default=None, help="PNG of the fit against the data (default: beside the fit file)")
    fi.add_argument("--quiet", action="store_true", help="no progress lines")
    fi.set_defaults(func=_identify)

    pl = sub.add_parser("plot", help="plot energy, energy balance and momenta from a results file",
                        description="Plot H, H + dissipated, the energy balance error and the momenta of a results file.")
    pl.add_argument("results", help="a results .h5 file")
    pl.add_argument("--out", default=None, help="PNG file (default: beside the results file)")
    pl.set_defaults(func=_plot)
    return p


class _Deprecated(argparse.Action):
    """An option's deprecated spelling: stores into the same place as the new one and
    notes the replacement (`args.deprecated`, printed once the options are accepted)."""

    def __init__(self, option_strings, dest, new, **kwargs):
        self.new = new
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        notes = list(getattr(namespace, "deprecated", None) or [])
        notes.append(f"{option_string} is deprecated, use {self.new}")
        namespace.deprecated = notes
        # messages about this option name it as it was written (`_options.flag`)
        namespace.spelled = {**(getattr(namespace, "spelled", None) or {}), self.dest: option_string}


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
    with warnings.catch_warnings(record=True) as refused:  # one line each, not Python's warning format
        warnings.simplefilter("always", jv.CacheWarning)
        jv.enable_compilation_cache()  # JAXVISCO_CACHE_DIR=DIR elsewhere, =off to disable
    for w in refused:
        if issubclass(w.category, jv.CacheWarning):
            print(f"{w.message}".replace("jaxvisco: ", "jaxvisco: warning: ", 1), file=sys.stderr)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    try:
        return args.func(args)
    except (ValueError, TypeError, FileNotFoundError, OSError, jv.SolverError) as e:
        msg = " ".join(str(e).split())
        print(f"jaxvisco: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxvisco: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
