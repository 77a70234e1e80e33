"""Floating-point policy, and JAX's persistent compilation cache.

jaxvisco computes in float64 only: energy balances to 1e-9 and Newton tolerances near
1e-10 are out of reach in float32. It never switches precision behind your back (no
import side effect); enable it yourself, before creating any array:

    import jax
    jax.config.update("jax_enable_x64", True)

or set the environment variable ``JAX_ENABLE_X64=1``. The command line does this for you.

jaxvisco's own compiled programs (`jit`) are compiled with `compiler_options()`.
"""

import contextlib
import functools
import os
import threading

import equinox as eqx
import jax
import numpy as np

from . import _export

__version__ = "0.2.0"  # jaxvisco.__version__ (defined here so that inner layers can read it)


def require_x64() -> None:
    """Check that JAX computes in float64, as jaxvisco needs (it never switches JAX's
    precision itself; every `Scene` checks this when it is built).

    **Raises:**

    `RuntimeError` naming the fix (`jax.config.update("jax_enable_x64", True)` or
    `JAX_ENABLE_X64=1`) when JAX runs in float32.
    """
    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError(
            "jaxvisco needs float64 but JAX runs in float32. Enable it before building "
            "meshes or scenes: `jax.config.update('jax_enable_x64', True)` or set "
            "JAX_ENABLE_X64=1 in the environment."
        )


def default_cache_dir():
    """Where `enable_compilation_cache` keeps compiled programs by default:
    ``$JAXVISCO_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxvisco``, else
    ``~/.cache/jaxvisco``. None when ``JAXVISCO_CACHE_DIR`` is ``off``."""
    env = os.environ.get("JAXVISCO_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("", "off", "0", "none") else os.path.expanduser(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxvisco")


def enable_compilation_cache(path: "str | os.PathLike | None" = None, *, shared: "bool | None" = None) -> "str | None":
    """Keep the compiled programs on disk, so that a new process neither traces nor
    compiles the time loops again.

    JAX's persistent compilation cache holds the compiled programs, and
    `jaxvisco-export/` inside it jaxvisco's traced ones (stored as data, never as
    pickles). A cache entry is a program this process runs, so whoever can write to the
    directory can run code as you: the directory is created private (mode 0700), and one
    that another user owns, or that group or others can write to (or a parent of it,
    unless sticky like `/tmp`), is refused with a `CacheWarning` that names it and the
    fix; the run then goes on without the cache.

    **Arguments:**

    - `path`: the cache directory (default `$JAXVISCO_CACHE_DIR`, else
      `$XDG_CACHE_HOME/jaxvisco`, else `~/.cache/jaxvisco`; `JAXVISCO_CACHE_DIR=off`
      turns the cache off).
    - `shared`: True to use a directory that others can write to on purpose (a group
      cache on a cluster): you then trust everyone who can write there. Default: True
      where the environment sets `JAXVISCO_CACHE_SHARED=1`, else False.

    Call it once, before the first `simulate`: it sets JAX's cache directory for the
    whole process and caches every program, also the small ones around the time loops.
    The `jaxvisco` command calls it for you.

    **Returns:**

    The directory, or None where the cache is off, refused or cannot be created (it
    never raises for those).

    **Example:**

    ```python
    import jaxvisco as jv

    path = jv.enable_compilation_cache("jaxvisco-cache")
    print(path)
    ```
    """
    import warnings

    path = default_cache_dir() if path is None else os.path.expanduser(os.fspath(path))
    if path is None:
        return None
    if shared is None:
        shared = os.environ.get("JAXVISCO_CACHE_SHARED", "").strip().lower() in ("1", "true", "yes", "on")
    try:
        _make_private(path)
    except OSError as e:
        warnings.warn(f"jaxvisco: no compilation cache: cannot create {path} ({e.strerror or e}); every run "
                      f"compiles afresh.", _export.CacheWarning, stacklevel=2)
        return None
    if shared:
        _export.trust(path)
    else:
        reason = _export.unsafe_reason(path)
        if reason is not None:
            warnings.warn(f"jaxvisco: compilation cache not used: {reason}. {_export._FIX}.", _export.CacheWarning,
                          stacklevel=2)
            return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path


def _make_private(path):
    """Create `path` and each missing directory above it with mode 0700."""
    missing = []
    p = os.path.abspath(path)
    while not os.path.isdir(p):
        missing.append(p)
        up = os.path.dirname(p)
        if up == p:
            break
        p = up
    for p in reversed(missing):
        with contextlib.suppress(FileExistsError):  # another process made it meanwhile
            os.mkdir(p, 0o700)


# XLA options for jaxvisco's own programs on CPU, each measured on its time loops:
# - YNNPACK kept to single dot products. XLA hands fused element-wise and reduction code
#   to its YNNPACK library by default; jaxvisco's kernels work on stacks of thousands of
#   3x3 tensors, where those library calls cost more than the loops XLA writes itself:
#   the eG(1) step of the 2D L-shape (refinement 4, lumped mass, h = 0.1) took 111-117 ms
#   against 148-163 ms (two runs each, alternating), the 3D L-shape (refinement 1)
#   46-56 ms against 58-66 ms; iteration counts alike, compile time alike.
# - XLA:CPU's loop emitters instead of its newer fusion emitters. The time loop of the
#   paper's L-shape (eG(1)) compiles to 357 kernels instead of 686, in 9.4 s instead of
#   14.8 s, and its steps are no slower: 2D r4 lumped eG(1) 38.2 against 40.4 ms, 3D r1
#   5.4 against 6.6 ms, 2D r4 eG(2) 55.9 against 61.0 ms (one alternating round, loaded
#   2-core VM; `benchmarks/step_cost.py --case`).
# - No tree reductions (XLA's `tree_reduction_rewriter` off). XLA:CPU splits every
#   reduction longer than 32 (the dot products of the Krylov solver, the sums over
#   quadrature points) into a `reduce-window` and a `reduce`, which its thunk runtime
#   compiles as kernels of their own: the paper scene's time loop (eG(1)) had 251 separately
#   compiled kernels, 185 without. Its XLA compile 5.55 / 5.81 / 5.73 s -> 5.18 / 5.48 /
#   5.31 s (alternating fresh processes, AMD EPYC, load ~1); steps no slower (three
#   alternating rounds, `benchmarks/revision_cost.py`, medians): 2D r4 lumped eG(1) 6.90
#   -> 5.92 ms, 3D r1 eG(1) 4.99 -> 4.56 ms, 2D r4 eG(2) 15.87 -> 15.95 ms. The sums
#   are then taken in order, in float64: every identity test passed unchanged.
_CPU_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT",
                "xla_cpu_use_fusion_emitters": False,
                "xla_disable_hlo_passes": "tree_reduction_rewriter"}


@functools.cache
def compiler_options() -> dict:
    """The XLA options jaxvisco compiles its own programs with.

    On CPU: XLA's loop emitters instead of its fusion emitters, single dot products for
    its YNNPACK library, no tree reductions (each only where this jaxlib knows the
    option); none on other backends, and none with `JAXVISCO_XLA_OPTIONS=off`. Programs
    of your own that contain jaxvisco's kernels (an ODE solver around
    `semidiscrete(scene).vector_field`, a loss around them) want them too: jaxvisco's
    3x3 products are written for the loop emitters, and with XLA's defaults they cost
    several times as much (the benchmarks pages have the measurements). Call it outside
    any JAX transformation (JAX takes compile options for top-level programs only).

    **Returns:**

    A dict for `jax.jit(..., compiler_options=...)`.

    **Example:**

    ```python
    import jax
    import jaxvisco as jv

    f = jax.jit(lambda x: 2.0 * x, compiler_options=jv.compiler_options())
    ```
    """
    if os.environ.get("JAXVISCO_XLA_OPTIONS", "").strip().lower() in ("off", "0", "none", "default"):
        return {}
    if jax.default_backend() != "cpu":  # measured on CPU only; GPUs want their tree reductions
        return {}
    with _PROBE_LOCK:  # threads that start programs at once (`jaxvisco paper`) probe once
        return dict(_probed_options())


_PROBE_LOCK = threading.Lock()


@functools.cache
def _probed_options():
    def known(options):
        try:
            jax.jit(lambda x: x + 1.0, compiler_options=options)(np.zeros(()))
        except Exception:  # noqa: BLE001 - an XLA that does not know an option
            return False
        return True

    # all at once first: one small program to compile where this jaxlib knows them all
    if known(_CPU_OPTIONS):
        return dict(_CPU_OPTIONS)
    return {key: value for key, value in _CPU_OPTIONS.items() if known({key: value})}


def device_array(value, dtype=None):
    """`value` (a Python number, a NumPy array) as a JAX array, put on the device without a
    compiled program; JAX arrays and tracers pass through (cast to `dtype` if given).

    Why: `jnp.asarray` of a host value runs a small program (`lax.stage`) that XLA compiles
    once per shape and dtype, 15-30 ms each. The arguments of a run and its trimmed results
    are host values, so a cold first `simulate` call compiled ten of them besides the
    time loop."""
    if isinstance(value, jax.Array):
        return value if dtype is None else value.astype(dtype)
    return jax.device_put(np.asarray(value, dtype=dtype))


def _top_level():
    """True outside every JAX trace (jit, grad, vmap, ...): only there may a program carry
    compile options. Asks a private JAX function; where it is missing, False (XLA's
    defaults, never an error)."""
    try:
        from jax._src.core import trace_state_clean
    except ImportError:
        return False
    return bool(trace_state_clean())


def jit(fn=None, *, export=False, plain=False):
    """`equinox.filter_jit(fn)`, compiled with `compiler_options()` when called at top
    level. Called inside a trace (e.g. `jax.grad` or `jax.jit` of a `simulate` call) it is
    a plain nested `filter_jit`: the options belong to the outermost program, which the
    caller compiles. `.lower(...)` as filter_jit's.

    `export=True` (the time loops): at top level, with JAX's persistent cache on
    (`enable_compilation_cache`), the traced program is kept on disk too and a later
    process skips tracing it (`_export`); calls the key cannot describe run as usual.
    Inside a trace the time loops are traced inline, not as a nested `filter_jit`: a
    derivative (`jax.grad`, `jax.jacfwd`) of a nested jit traces its body plainly first
    and differentiates that jaxpr, so the loop was traced twice, once for nothing (its
    custom derivative's rule traces it again).

    `plain=True`: `jax.jit` instead of `filter_jit` (every argument an array): the least
    call overhead, for functions a host-driven solver calls thousands of times."""
    if fn is None:
        return functools.partial(jit, export=export, plain=plain)
    variants = {}

    def get():
        # One variant per set of options (none inside a trace), so that it always matches
        # `compiler_options()`, as the exported path does (its key holds the options).
        opts = compiler_options() if _top_level() else {}
        key = tuple(sorted(opts.items()))
        if key not in variants:
            variants[key] = (jax.jit if plain else eqx.filter_jit)(fn, compiler_options=opts or None)
        return variants[key]

    name = f"{fn.__module__}.{fn.__qualname__}"

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if export:
            if not _top_level():
                return fn(*args, **kwargs)
            if _export.directory() is not None:
                try:
                    return _export.call(fn, name, args, kwargs, compiler_options())
                except _export.Uncacheable:
                    pass
        return get()(*args, **kwargs)

    def ahead(*args, **kwargs):
        """Trace (or, exported, load) the program of a call ahead of it, without compiling:
        returns the `Lowered` program to compile, or None where the exported path holds it."""
        if export and _top_level() and _export.directory() is not None:
            try:
                _export.prepare(fn, name, args, kwargs, compiler_options())
                return None
            except _export.Uncacheable:
                pass
        return get().lower(*args, **kwargs)

    call.lower = lambda *args, **kwargs: get().lower(*args, **kwargs)
    call.ahead = ahead
    return call
