"""Traced programs kept on disk (`jax.export`), so that a new process skips tracing.

JAX's persistent compilation cache (`enable_compilation_cache`) spares a new process the
XLA compile of the time loop, but not the Python tracing and lowering that come before
it: measured on the paper's L-shape (2D r1, eG(1), h = 0.1, 2-core VM), a second process's
first `simulate` call took 4.2-5.6 s, of which 2.8-3.6 s tracing `_run`, 0.8 s lowering it
to StableHLO and 0.7-0.8 s fetching the compiled program. This module stores the lowered
program itself (`jax.export`, serialized StableHLO) next to JAX's cache, keyed by
everything the trace depended on; a later process deserializes it and hands it to XLA,
whose compiled form then comes from JAX's cache as before.

The key is a SHA-256 of: jaxvisco's source files, the versions of jax/jaxlib/equinox,
the x64 flag, the backend, jaxvisco's environment switches, the program's name, the
shapes/dtypes of every array argument and a pickle of every other (static) part of the
arguments. A static part that cannot be named safely across processes (a lambda, a
closure, a function or class defined outside jaxvisco/jax/equinox/numpy, e.g. in
``__main__``, whose code the key would not see) makes the call *uncacheable*: it runs
as before (traced, compiled, with JAX's cache), never from a stale entry.

Host factorizations: the program names its sparsity pattern by a hash (`HostLU.key`,
see `_sparse`). The patterns built while tracing are recorded (`record_pattern`) and
stored with the entry; loading it builds them again and checks their keys.

Entries are written to a temporary file and renamed into place (a killed process leaves
no partial entry); an entry that does not load is ignored and written again.
"""

import contextlib
import functools
import hashlib
import importlib.metadata
import io
import os
import pickle
import sys
import threading
import types

import equinox as eqx
import jax

_FORMAT = 1
_SAFE_MODULES = ("jaxvisco", "equinox", "jax", "jaxlib", "numpy", "builtins", "math", "operator", "functools",
                 "collections", "typing", "enum", "dataclasses", "abc", "copyreg")
_LU_TARGETS = ("jaxvisco_lu_factor", "jaxvisco_lu_solve")
_recorder = threading.local()  # .patterns: list of (builder name, args) while this thread exports a program
_memory = {}  # key -> loaded entry, or None for an uncacheable program (this process)
stats = {"exported": 0, "loaded": 0, "uncacheable": 0}  # counts in this process (tests read them)


def clear():
    """Forget this process's loaded programs (the files stay). The key sees jaxvisco's
    source files, not objects patched at run time: clear after patching its internals."""
    _memory.clear()


class Uncacheable(Exception):
    """A static argument that the key cannot describe safely."""


# Registered by the layers above (this module is infrastructure and imports none of
# them): builders of host factorization patterns by name, and checks that may refuse
# to export (each returns None or the reason).
_BUILDERS = {}
_CHECKS = []


def register_pattern(name, builder):
    """Make `builder(*args)` (e.g. `_tangent.position_pattern`) the way to rebuild the
    patterns recorded under `name` when a stored program is loaded."""
    _BUILDERS[name] = builder


def register_check(check):
    """`check()` -> None, or why no program may be exported now (e.g. `_sparse`: the
    callback backend)."""
    _CHECKS.append(check)


def record_pattern(name, args):
    """Called by the builders of host factorization patterns (`_tangent.position_pattern`)."""
    patterns = getattr(_recorder, "patterns", None)
    if patterns is not None:
        patterns.append((name, args))


def _builders():
    return _BUILDERS


class _KeyPickler(pickle.Pickler):
    """Pickles the static part of a call, refusing what would name code it cannot see."""

    def reducer_override(self, obj):
        if isinstance(obj, (types.FunctionType, types.BuiltinFunctionType, types.MethodType, type)):
            module = getattr(obj, "__module__", None) or ""
            qual = getattr(obj, "__qualname__", "") or ""
            if module.split(".")[0] not in _SAFE_MODULES or "<lambda>" in qual or "<locals>" in qual:
                raise Uncacheable(f"{module}.{qual}")
        return NotImplemented


def _dumps(obj):
    buf = io.BytesIO()
    try:
        _KeyPickler(buf, protocol=4).dump(obj)
    except Uncacheable:
        raise
    except Exception as e:  # noqa: BLE001 - anything pickle refuses
        raise Uncacheable(repr(e)) from e
    return buf.getvalue()


class _Aval:
    """Shape, dtype and weak type of an array argument (a leaf in the key's skeleton)."""

    __slots__ = ("shape", "dtype", "weak")

    def __init__(self, a):
        self.shape, self.dtype = tuple(a.shape), str(a.dtype)
        self.weak = bool(getattr(a, "weak_type", False))

    def __reduce__(self):
        return (tuple, ((self.shape, self.dtype, self.weak),))


class _Leaf:
    """Placeholder for an array output in a stored output skeleton."""


@functools.cache
def _source_digest():
    root = os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha256()
    for dirpath, dirnames, files in os.walk(root):
        dirnames.sort()
        for f in sorted(files):
            if f.endswith((".py", ".cc")):
                p = os.path.join(dirpath, f)
                h.update(os.path.relpath(p, root).encode())
                with open(p, "rb") as fh:
                    h.update(fh.read())
    return h.hexdigest()


@functools.cache
def _versions():  # ~3 ms of package metadata lookups: once per process, not per call
    out = []
    for dist in ("jax", "jaxlib", "equinox"):
        try:
            out.append(importlib.metadata.version(dist))
        except importlib.metadata.PackageNotFoundError:
            out.append(None)
    return out


def directory():
    """Where exported programs go: ``jaxvisco-export`` in JAX's persistent cache
    directory, or None while that cache is off or ``JAXVISCO_EXPORT=off``."""
    base = jax.config.jax_compilation_cache_dir
    if not base or os.environ.get("JAXVISCO_EXPORT", "").strip().lower() in ("off", "0", "none"):
        return None
    return os.path.join(base, "jaxvisco-export")


def _key(name, static, skeleton, options):
    env = sorted((k, v) for k, v in os.environ.items() if k.startswith("JAXVISCO_") and k != "JAXVISCO_CACHE_DIR")
    head = (_FORMAT, name, _source_digest(), _versions(), sys.version_info[:2], bool(jax.config.read("jax_enable_x64")),
            jax.default_backend(), env, sorted(options.items()))
    return hashlib.sha256(pickle.dumps(head, protocol=4) + _dumps((static, skeleton))).hexdigest()


def _write(path, entry):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = f"{path}.{os.getpid()}.tmp"
    try:
        with open(tmp, "wb") as f:
            pickle.dump(entry, f, protocol=4)
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)


def _load(path):
    try:
        with open(path, "rb") as f:
            entry = pickle.load(f)
        if entry.get("format") != _FORMAT:
            return None
        builders = _builders()
        entry["hosts"] = [builders[b](*a) for b, a in entry["patterns"]]  # alive while the entry is
        if [h.key for h in entry["hosts"]] != entry["pattern_keys"]:
            return None
        entry["exported"] = jax.export.deserialize(bytearray(entry["hlo"]))
        return entry
    except Exception:  # noqa: BLE001 - a damaged or foreign entry is a miss
        return None


def _export(fn, name, leaves, in_def, static, options):
    """Trace `fn` once through `jax.export`: the entry (serialized program, the host
    patterns it names, the static part and structure of its output)."""
    out_static = {}

    def flat(*xs):
        args, kwargs = eqx.combine(jax.tree_util.tree_unflatten(in_def, xs), static)
        out = fn(*args, **kwargs)
        dyn, st = eqx.partition(out, eqx.is_array)
        out_static["static"] = st
        out_static["skeleton"] = jax.tree_util.tree_map(lambda _: _Leaf(), dyn)
        return jax.tree_util.tree_leaves(dyn)

    checks = [jax.export.DisabledSafetyCheck.custom_call(t) for t in _LU_TARGETS]
    prev = getattr(_recorder, "patterns", None)
    _recorder.patterns = []
    try:
        exp = jax.export.export(jax.jit(flat), disabled_checks=checks)(*leaves)
        patterns = list(_recorder.patterns)
    finally:
        _recorder.patterns = prev
    builders = _builders()
    hosts = [builders[b](*a) for b, a in patterns]
    entry = dict(format=_FORMAT, name=name, hlo=bytes(exp.serialize()), patterns=patterns,
                 pattern_keys=[h.key for h in hosts], out_static=out_static["static"],
                 out_skeleton=out_static["skeleton"], hosts=hosts)
    entry["exported"] = exp
    return entry


def call(fn, name, args, kwargs, options):
    """`fn(*args, **kwargs)` as a compiled program, from an exported entry where one is
    stored (exporting and storing it otherwise). Raises `Uncacheable` where the key
    cannot describe the static arguments; the caller then runs `fn` the usual way."""
    folder = directory()
    if folder is None:
        raise Uncacheable("no persistent cache directory")
    for check in _CHECKS:
        reason = check()
        if reason is not None:
            raise Uncacheable(reason)
    dyn, static = eqx.partition((args, kwargs), eqx.is_array)
    leaves, in_def = jax.tree_util.tree_flatten(dyn)
    skeleton = jax.tree_util.tree_map(_Aval, dyn)
    try:
        key = _key(name, static, skeleton, options)
    except Uncacheable:
        stats["uncacheable"] += 1
        raise
    if key in _memory and _memory[key] is None:
        raise Uncacheable("refused before in this process")
    entry = _memory.get(key)
    path = os.path.join(folder, f"{name}-{key[:32]}.jvx")
    if entry is None and os.path.exists(path):
        entry = _load(path)
        stats["loaded"] += entry is not None
    if entry is None:
        try:
            entry = _export(fn, name, leaves, in_def, static, options)
        except Exception as e:  # noqa: BLE001 - whatever jax.export refuses runs the usual way
            _memory[key] = None
            stats["uncacheable"] += 1
            raise Uncacheable(f"jax.export refused the program: {e!r}") from e
        stats["exported"] += 1
        try:
            _write(path, {k: v for k, v in entry.items() if k not in ("exported", "hosts")})
        except (OSError, pickle.PicklingError, TypeError, AttributeError):
            pass  # a read-only or full cache directory: run without storing
    _memory[key] = entry
    runner = entry.get("runner")
    if runner is None:
        exported = entry["exported"]

        def run(*xs):
            return exported.call(*xs)

        run.__name__ = run.__qualname__ = "exported_" + name.rsplit(".", 1)[-1]
        runner = entry["runner"] = jax.jit(run, compiler_options=options or None)
    # Committed (outputs of an earlier run) and uncommitted (new) arrays would compile the
    # exported program twice (seen: the command line's chunks); commit every input.
    out_leaves = runner(*jax.device_put(leaves, jax.devices()[0]))
    dyn_out = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(entry["out_skeleton"]), out_leaves)
    return eqx.combine(dyn_out, entry["out_static"])
