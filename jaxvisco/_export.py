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
Entries hold data, never code: a small header in JSON (the name, the full key, the host
patterns, the static part and structure of the output, described by `_to_data`: numbers,
strings, containers, arrays and the registered output classes) and the serialized
program (`jax.export`'s flatbuffer). Nothing read back from disk is unpickled, and an
entry whose header names anything else, whose key is not the one asked for, or that
does not parse is a miss. JAX's own entries in the same directory are compiled programs;
`_config.enable_compilation_cache` therefore only uses a directory that no other user
can write (see `safe_directory`).
"""

import base64
import contextlib
import dataclasses
import functools
import hashlib
import importlib.metadata
import io
import json
import os
import pickle
import stat
import sys
import threading
import types

import equinox as eqx
import jax
import numpy as np

_FORMAT = 2
_MAGIC = b"JVX2\n"  # then 8 bytes of header length, the JSON header, the serialized program
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
    directory, or None while that cache is off, ``JAXVISCO_EXPORT=off``, or the
    directory is one that others could write (`unsafe_reason`; warned once)."""
    base = jax.config.jax_compilation_cache_dir
    if not base or os.environ.get("JAXVISCO_EXPORT", "").strip().lower() in ("off", "0", "none"):
        return None
    folder = os.path.join(base, "jaxvisco-export")
    reason = None if base in _TRUSTED else unsafe_reason(folder if os.path.isdir(folder) else base)
    if reason is not None:
        if base not in _WARNED:
            _WARNED.add(base)
            import warnings

            warnings.warn(f"jaxvisco: traced programs are not cached: {reason}. {_FIX}.", CacheWarning, stacklevel=3)
        return None
    return folder


class CacheWarning(UserWarning):
    """The warning `enable_compilation_cache` gives when it refuses a cache directory
    (another user owns it, or others can write to it) or cannot create one; the message
    names the directory and the fix, and the run goes on without the cache."""


_TRUSTED = set()  # directories declared shared and trusted (`enable_compilation_cache(shared=True)`)
_WARNED = set()
_FIX = ("Fix: `chmod 700` it (and its parents: no write access for group or others) or choose another "
        "JAXVISCO_CACHE_DIR; a deliberately shared cache needs enable_compilation_cache(path, shared=True) "
        "or JAXVISCO_CACHE_SHARED=1, and trusts everyone who can write to it")


def trust(path):
    """Use `path` even where others can write to it (`enable_compilation_cache(shared=True)`)."""
    _TRUSTED.add(os.fspath(path))


def _owner(uid):
    try:
        import pwd

        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except (ImportError, KeyError):
        return f"uid {uid}"


def unsafe_reason(path):
    """Why the directory `path` must not hold programs that this process will run, or
    None. Whoever can write a cache entry can run code as every user of the cache (JAX's
    entries are compiled machine code), so, as ssh's StrictModes does for key files: the
    directory must belong to this user and be writable by nobody else, and each directory
    above it must belong to this user or root and be writable by nobody else unless its
    sticky bit is set (``/tmp``: others cannot rename what is ours). No check where the
    platform has no user ids."""
    if not hasattr(os, "getuid"):
        return None
    uid = os.getuid()
    real = os.path.realpath(path)
    try:
        st = os.stat(real)
    except OSError as e:
        return f"{path} cannot be read ({e.strerror})"
    mode = stat.S_IMODE(st.st_mode)
    if st.st_uid != uid:
        return f"{path} (mode {mode:o}) is owned by {_owner(st.st_uid)}, not by you"
    if mode & 0o022:
        return f"{path} (mode {mode:o}, owner {_owner(st.st_uid)}) is writable by group or others"
    parent = os.path.dirname(real)
    while True:
        st = os.stat(parent)
        pmode = stat.S_IMODE(st.st_mode)
        if st.st_uid not in (uid, 0):
            return f"{path}: its parent {parent} (mode {pmode:o}) is owned by {_owner(st.st_uid)}"
        if pmode & 0o022 and not pmode & stat.S_ISVTX:
            return f"{path}: its parent {parent} (mode {pmode:o}, owner {_owner(st.st_uid)}) is writable by group or others"
        up = os.path.dirname(parent)
        if up == parent:
            return None
        parent = up


def _key(name, static, skeleton, options):
    env = sorted((k, v) for k, v in os.environ.items()
                 if k.startswith("JAXVISCO_") and k not in ("JAXVISCO_CACHE_DIR", "JAXVISCO_CACHE_SHARED"))
    head = (_FORMAT, name, _source_digest(), _versions(), sys.version_info[:2], bool(jax.config.read("jax_enable_x64")),
            jax.default_backend(), env, sorted(options.items()))
    return hashlib.sha256(pickle.dumps(head, protocol=4) + _dumps((static, skeleton))).hexdigest()


class Unstorable(Exception):
    """A part of an entry that `_to_data` cannot describe as data."""


_TYPES = {}  # name -> class: the output classes an entry may rebuild (`register_type`)
_WRAPPERS = {}  # name -> class: array wrappers (`register_wrapper`)


def register_type(cls):
    """Let stored entries rebuild instances of `cls` (an `equinox.Module` that a cached
    program returns, e.g. `Solution`) from their fields; returns `cls` (a decorator)."""
    _TYPES[f"{cls.__module__}.{cls.__qualname__}"] = cls
    return cls


def register_wrapper(cls):
    """Let stored entries hold instances of `cls`, a wrapper of one NumPy array (its
    ``array`` attribute, rebuilt by ``cls(array)``, e.g. `StaticArray`); returns `cls`."""
    _WRAPPERS[f"{cls.__module__}.{cls.__qualname__}"] = cls
    return cls


def _to_data(obj):
    """`obj` as JSON-ready data: None, bools, numbers, strings, tuples, lists, dicts with
    string keys, numeric NumPy arrays, `StaticArray`-like wrappers, output placeholders and
    the registered classes (by their fields). Anything else raises `Unstorable`."""
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (int, float)) and type(obj) in (int, float):
        return obj
    if isinstance(obj, np.generic):
        return _to_data(np.asarray(obj)[()].item()) if obj.dtype.kind in "biuf" else _refuse(obj)
    if isinstance(obj, tuple) and type(obj) is tuple:
        return {"tuple": [_to_data(o) for o in obj]}
    if isinstance(obj, list) and type(obj) is list:
        return {"list": [_to_data(o) for o in obj]}
    if isinstance(obj, dict) and type(obj) is dict and all(isinstance(k, str) for k in obj):
        return {"dict": {k: _to_data(v) for k, v in obj.items()}}
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "biuf" or obj.dtype.byteorder == ">":
            _refuse(obj)
        a = np.ascontiguousarray(obj)
        return {"array": [a.dtype.str, list(a.shape), base64.b64encode(a.tobytes()).decode("ascii")]}
    if isinstance(obj, _Leaf):
        return {"leaf": 0}
    name = f"{type(obj).__module__}.{type(obj).__qualname__}"
    if _WRAPPERS.get(name) is type(obj):
        return {"wrapper": name, "array": _to_data(obj.array)}
    if _TYPES.get(name) is type(obj):
        return {"module": name, "fields": {f.name: _to_data(getattr(obj, f.name)) for f in dataclasses.fields(obj)}}
    return _refuse(obj)


def _refuse(obj):
    raise Unstorable(f"{type(obj).__module__}.{type(obj).__qualname__}")


def _from_data(d):
    """The inverse of `_to_data`; raises `ValueError` on anything it does not describe."""
    if d is None or isinstance(d, (bool, int, float, str)):
        return d
    if not isinstance(d, dict) or len(d) not in (1, 2):
        raise ValueError("not an entry's data")
    if "tuple" in d:
        return tuple(_from_data(o) for o in d["tuple"])
    if "list" in d:
        return [_from_data(o) for o in d["list"]]
    if "dict" in d:
        return {str(k): _from_data(v) for k, v in d["dict"].items()}
    if "wrapper" in d:
        cls = _WRAPPERS.get(d["wrapper"])
        if cls is None:
            raise ValueError(f"unknown wrapper {d['wrapper']!r}")
        array = _from_data(d["array"])
        if not isinstance(array, np.ndarray):
            raise ValueError("a wrapper holds an array")
        return cls(array)
    if "array" in d:
        dtype, shape, data = d["array"]
        dtype = np.dtype(dtype)
        if dtype.kind not in "biuf":
            raise ValueError(f"array of {dtype}")
        a = np.frombuffer(base64.b64decode(data, validate=True), dtype=dtype).reshape([int(n) for n in shape])
        return a.copy()
    if "leaf" in d:
        return _Leaf()
    if "module" in d:
        cls = _TYPES.get(d["module"])
        if cls is None:
            raise ValueError(f"unknown class {d['module']!r}")
        names = [f.name for f in dataclasses.fields(cls)]
        fields = d["fields"]
        if sorted(fields) != sorted(names):
            raise ValueError(f"fields of {d['module']} differ")
        obj = object.__new__(cls)
        for n in names:  # the fields as data, no __init__, __setstate__ or any code of the entry's choosing
            object.__setattr__(obj, n, _from_data(fields[n]))
        return obj
    raise ValueError("not an entry's data")


def _write(path, header, program):
    """Store an entry atomically: a temporary file renamed into place."""
    os.makedirs(os.path.dirname(path), mode=0o700, exist_ok=True)
    head = json.dumps(header, separators=(",", ":"), allow_nan=False).encode()
    tmp = f"{path}.{os.getpid()}.tmp"
    try:
        with open(tmp, "wb") as f:
            f.write(_MAGIC + len(head).to_bytes(8, "little") + head + program)
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)


def _load(path, key):
    """The entry stored at `path` for `key`, or None (a miss: absent, damaged, foreign,
    of another key or format)."""
    try:
        with open(path, "rb") as f:
            blob = f.read()
        if not blob.startswith(_MAGIC):
            return None
        n = int.from_bytes(blob[len(_MAGIC):len(_MAGIC) + 8], "little")
        start = len(_MAGIC) + 8
        header = json.loads(blob[start:start + n].decode())
        if not isinstance(header, dict) or header.get("format") != _FORMAT or header.get("key") != key:
            return None
        entry = {k: _from_data(header[k]) for k in ("patterns", "pattern_keys", "out_static", "out_skeleton")}
        builders = _builders()
        entry["hosts"] = [builders[b](*a) for b, a in entry["patterns"]]  # alive while the entry is
        if [h.key for h in entry["hosts"]] != entry["pattern_keys"]:
            return None
        entry["exported"] = jax.export.deserialize(bytearray(blob[start + n:]))
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
        specs = [jax.ShapeDtypeStruct(x.shape, x.dtype, weak_type=getattr(x, "weak_type", False))
                 if isinstance(x, jax.core.Tracer) else x for x in leaves]  # inside a trace (`nested`)
        exp = jax.export.export(jax.jit(flat), disabled_checks=checks)(*specs)
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
    entry, leaves = prepare(fn, name, args, kwargs, options)
    runner = entry.get("runner")
    if runner is None:
        exported = entry["exported"]

        def run(*xs):
            return exported.call(*xs)

        run.__name__ = run.__qualname__ = "exported_" + name.rsplit(".", 1)[-1]
        runner = entry["runner"] = jax.jit(run, compiler_options=options or None)
    # Committed (outputs of an earlier run) and uncommitted (new) arrays would compile the
    # exported program twice (seen: the command line's chunks); commit every input.
    return _rebuild(entry, runner(*jax.device_put(leaves, jax.devices()[0])))


def _rebuild(entry, out_leaves):
    """The output of `entry`'s function from the array outputs of its program."""
    dyn_out = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(entry["out_skeleton"]), out_leaves)
    return eqx.combine(dyn_out, entry["out_static"])


def _plain(x):
    """`x` is an array, or a tracer of a program being traced (not of a derivative or a
    batch, which an exported program's call cannot follow)."""
    if not isinstance(x, jax.core.Tracer):
        return True
    try:
        from jax._src.interpreters.partial_eval import DynamicJaxprTracer
    except ImportError:  # a JAX that moved it: trace as usual
        return False
    return isinstance(x, DynamicJaxprTracer)


def nested(fn, name, args, kwargs):
    """`fn(*args, **kwargs)` inside a program being traced (e.g. the user's `jax.jit` of a
    `jax.grad` of a run: the derivative's recording loop and its sweeps) as the call of an
    exported program, loaded where one is stored (exporting and storing it otherwise): a
    later process loads it instead of tracing and lowering `fn`, and the program around
    it, which inlines it, is the one JAX's cache already holds. Raises `Uncacheable` where
    `call` does, inside another export (that program holds this one), and where an
    argument is differentiated or batched by a transformation inside the program; the
    caller then traces `fn` as usual."""
    if getattr(_recorder, "patterns", None) is not None:
        raise Uncacheable("inside the export of another program")
    if not all(_plain(x) for x in jax.tree_util.tree_leaves((args, kwargs))):
        raise Uncacheable("an argument is transformed (differentiated or batched) inside the program")
    entry, leaves = prepare(fn, name, args, kwargs, {})
    return _rebuild(entry, entry["exported"].call(*leaves))


def inline(fn, *args, **kwargs):
    """`fn(*args, **kwargs)`, by `nested` where the persistent cache is on and the call can
    be stored, else traced as usual."""
    if directory() is not None:
        try:
            return nested(fn, f"{fn.__module__}.{fn.__qualname__}", args, kwargs)
        except Uncacheable:
            pass
    return fn(*args, **kwargs)


def prepare(fn, name, args, kwargs, options):
    """What `call` runs, ahead of it: the entry of `fn` at these arguments, loaded or
    traced and stored (the Python half of a first call: a caller that traces several
    programs in threads does this one at a time), and the arguments' array leaves.
    Raises `Uncacheable` as `call`."""
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
        entry = _load(path, key)
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
            header = dict(format=_FORMAT, name=name, key=key,
                          **{k: _to_data(entry[k]) for k in ("patterns", "pattern_keys", "out_static", "out_skeleton")})
            _write(path, header, entry["hlo"])
        except (OSError, Unstorable, ValueError):
            pass  # a read-only or full cache directory, or an output it cannot describe: run without storing
    _memory[key] = entry
    return entry, leaves
