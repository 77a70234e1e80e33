"""Sparse direct factorization on the host, callable from compiled JAX code.

XLA on CPU has no sparse LU, so the assembled tangent of the position block is factored
by SuperLU (scipy) on the host. A factorization lives in a small host cache and is
referred to by an integer token that travels in the compiled loop's carry: this is what
lets one factorization be reused across Newton iterations and time steps. A singular
matrix gives the token -1 and solves with it return NaN, which the Newton loop treats as
a failed step.

How compiled code reaches the host: by default through two XLA foreign-function targets
(`jaxvisco/_solver/_ffi/hostlu.cc`, built by ``pip install .``) that hand their buffers to
`_host_call` here. They are referred to by name, so JAX's persistent compilation cache
stores the programs that use them; with `jax.pure_callback` (the fallback when the
extension is missing, or with ``JAXVISCO_HOST_LU=callback``) JAX refuses to cache a
program ("uses host callbacks") and every process recompiles the time loop. A pattern is
named in the program by a hash of its sparsity pattern (`HostLU.key`), so a cached
program finds its pattern again in a new process.

Where the extension is built, SuperLU's triangular factors of up to `PUBLISH_NNZ`
nonzeros are handed to it after each factorization (`_triangular_factors`), SuperLU's
own object is dropped, and every solve with them runs there, in C++ without the GIL, on
both paths (so both give identical results). Larger factors stay with SuperLU, whose
supernodes (dense blocks) need less memory traffic per solve than compressed columns.
Without the extension SuperLU solves everything (`HostLU.solve`).
"""

import collections
import concurrent.futures
import functools
import hashlib
import itertools
import os
import threading
import warnings
import weakref

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from .._export import register_check

try:
    from ._ffi import _hostlu
except ImportError as _missing:  # built without the extension: the pure_callback path
    _hostlu = None
    if os.environ.get("JAXVISCO_HOST_LU") != "callback":  # unless that path was chosen
        warnings.warn(
            f"jaxvisco was installed without its C++ extension ({_missing}). It runs, with the same results, but "
            "its host sparse LU goes through jax.pure_callback, so the compilation cache cannot keep the compiled "
            "programs (every new process compiles them again, several seconds each). Fix: install a C++ compiler "
            "(e.g. g++) and reinstall jaxvisco (pip install --force-reinstall --no-deps .); or set "
            "JAXVISCO_HOST_LU=callback to use this path without this warning.", RuntimeWarning)

BACKENDS = ("ffi", "callback")
# Tokens are unique in the process, not per pattern: a pattern's store made again (same
# key) never reuses a token that an older one published, or its finalizer would retract it.
_TOKENS = itertools.count()
_REGISTRY = weakref.WeakValueDictionary()  # HostLU.key -> HostLU


def backend():
    """The host LU path compiled into new programs: "ffi" (cacheable, the default where
    the extension is built) or "callback" (`jax.pure_callback`; also forced with the
    environment variable ``JAXVISCO_HOST_LU=callback``)."""
    choice = os.environ.get("JAXVISCO_HOST_LU", "ffi" if _hostlu is not None else "callback")
    if choice not in BACKENDS:
        raise ValueError(f"JAXVISCO_HOST_LU must be one of {BACKENDS}, got {choice!r}.")
    if choice == "ffi" and _hostlu is None:
        raise ValueError("JAXVISCO_HOST_LU=ffi, but jaxvisco was installed without its extension "
                         "(jaxvisco._solver._ffi._hostlu); reinstall with a C++ compiler, or use JAXVISCO_HOST_LU=callback.")
    return choice


def _exportable():
    """`_export`'s check: `jax.export` cannot serialize host callbacks."""
    return None if backend() == "ffi" else "host callbacks (JAXVISCO_HOST_LU=callback) cannot be exported"


register_check(_exportable)


RETAIN = 64  # factorizations a plain run keeps alive (its reused tangent needs 1-2)

# Factors (nonzeros of L and U) that the extension takes over. One solve with SuperLU's
# object / with the extension's compressed columns (L-shape, eG(1) position blocks, us,
# from Python):
#   2D r3    n 800     36 576 nonzeros      58 / 24
#   2D r4    n 1 378   78 606              98 / 50
#   3D r1    n 672     84 965              67 / 50
#   3D r2    n 3 969   1 346 227           824 / 879
#   3D r3    n 12 000  8 236 823           9 764 / 11 525
# and a solve through SuperLU in the compiled loop pays ~150 us for its trip through
# Python besides (2D r4: 255 us against 98 us from Python). A step of the 2D L-shape
# (refinement 4, lumped mass, eG(1), h = 0.1, 6 solves a step): 9.8 -> 8.5-8.8 ms
# (120 steps, alternating processes, the same iterations).
PUBLISH_NNZ = 2_000_000


class HostLU:
    """Factorizations of matrices with one fixed sparsity pattern (COO rows/cols).

    The store keeps the most recently used factorizations: at least as many as the
    program that factors asks for (`retain`, a constant of each factor call: `RETAIN`
    for a plain run, a checkpointed segment's worth when the run is differentiated) and
    at most `max_bytes` of them."""

    def __init__(self, rows, cols, n, max_bytes=2 * 2**30):
        rows = np.asarray(rows, dtype=np.int64).ravel()
        cols = np.asarray(cols, dtype=np.int64).ravel()
        key = cols * n + rows
        uniq, self._inverse = np.unique(key, return_inverse=True)
        self._indices = (uniq % n).astype(np.int32)
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(uniq // n, minlength=n))]).astype(np.int32)
        self.n = n
        self.nnz = len(uniq)
        digest = hashlib.blake2b(np.int64(n).tobytes() + rows.tobytes() + cols.tobytes(), digest_size=8).digest()
        self.key = int.from_bytes(digest, "little") & (2**63 - 1)
        _REGISTRY[self.key] = self
        self._cache = collections.OrderedDict()
        self._retain = RETAIN
        self._max_bytes = max_bytes
        self._bytes = collections.OrderedDict()
        self._lock = threading.Lock()  # the store's bookkeeping (factors and solves run on different threads)
        # Where the extension is built, factors are published to it and solved there (no
        # Python in a compiled solve, on either path); its copies go with this pattern.
        self._published = set()
        if _hostlu is not None:
            weakref.finalize(self, _retract_all, _hostlu, self.key, self._published)

    def matrix(self, data):
        vals = np.bincount(self._inverse, weights=np.asarray(data, dtype=np.float64).ravel(), minlength=self.nnz)
        return sp.csc_matrix((vals, self._indices, self._indptr), shape=(self.n, self.n))

    # Fill-reducing ordering: minimum degree on the pattern of A^T + A, which suits the
    # structurally symmetric element patterns. Measured on the 3D L-shape (hex8 r4, 26 871
    # position DOFs, eG(1)): factor 7.08 -> 4.51 s and one solve 43 -> 33 ms against
    # SuperLU's default COLAMD (benchmarks/profile_step.py --dim 3 ...).
    permc_spec = "MMD_AT_PLUS_A"

    def factor(self, data, retain=RETAIN):
        """Factor the matrix with COO values `data`; keep at least the `retain` most
        recently used factorizations (and at most `max_bytes`). Returns the token."""
        try:
            lu = spla.splu(self.matrix(data), permc_spec=self.permc_spec)
        except RuntimeError:  # exactly singular
            return np.int64(-1)
        nbytes = 12 * (lu.L.nnz + lu.U.nnz)
        token = next(_TOKENS)
        if _hostlu is not None and lu.L.nnz + lu.U.nnz <= PUBLISH_NNZ:  # the extension solves from here on
            _hostlu.publish(self.key, token, self.n, *_triangular_factors(lu))
            self._published.add(token)
            lu = _PUBLISHED
        with self._lock:
            self._cache[token] = lu
            self._bytes[token] = nbytes
            self._retain = max(int(retain), 1)
            if len(self._cache) > self._retain or sum(self._bytes.values()) > self._max_bytes:
                self._evict(keep=token)
        return np.int64(token)

    def _evict(self, keep):
        """Drop the least recently used factorizations but `keep` (the one just made) down
        to `retain` and `max_bytes`. Published ones are used where the extension solves:
        its clock orders them."""
        order = ([t for t in self._cache if t not in self._published]
                 + sorted(self._published, key=lambda t: _hostlu.last_use(self.key, t)))
        for old in (t for t in order if t != keep):
            if len(self._cache) <= self._retain and sum(self._bytes.values()) <= self._max_bytes:
                break
            del self._cache[old], self._bytes[old]
            if old in self._published:
                self._published.discard(old)
                _hostlu.retract(self.key, old)

    def solve(self, token, b, trans=False):
        token = int(token)
        if token < 0:  # singular: the caller sees NaN and rejects the step
            return np.full(b.shape, np.nan)
        with self._lock:
            lu = self._cache.get(token)
            if lu is not None:
                self._cache.move_to_end(token)  # least recently *used* goes first
                self._bytes.move_to_end(token)
        if lu is None:
            raise RuntimeError(
                f"jaxvisco: factorization {token} is no longer cached (the last factor call kept the "
                f"{self._retain} most recent ones, at most {self._max_bytes / 2**30:.1f} GiB). "
                "Raise NewtonKrylov(retain=...) if a program needs more factorizations alive at once.")
        b = np.ascontiguousarray(b, dtype=np.float64)
        if lu is _PUBLISHED:
            x = np.empty_like(b)
            if not _hostlu.solve(self.key, token, b, x, bool(trans)):
                raise RuntimeError(f"jaxvisco: factorization {token} of pattern {self.key} is not published.")
            return x
        return lu.solve(b, trans="T" if trans else "N")


_PUBLISHED = object()  # the store's entry for a factorization the extension holds


def _triangular_factors(lu):
    """SuperLU's factors as the extension keeps them: L strictly below and U strictly
    above the diagonal as compressed columns (int64 pointers, int32 rows, sorted), U's
    diagonal, perm_r, perm_c (``P_r A P_c = L U``)."""
    L = sp.tril(lu.L, -1, format="csc")
    U = lu.U.tocsc()
    Us = sp.triu(U, 1, format="csc")
    L.sort_indices()
    Us.sort_indices()
    ptr = lambda m: np.ascontiguousarray(m.indptr, dtype=np.int64)  # noqa: E731
    idx = lambda a: np.ascontiguousarray(a, dtype=np.int32)  # noqa: E731
    val = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    return (ptr(L), idx(L.indices), val(L.data), ptr(Us), idx(Us.indices), val(Us.data), val(U.diagonal()),
            idx(lu.perm_r), idx(lu.perm_c))


# SuperLU factorizations run on one dedicated host thread. XLA calls the callbacks from
# its own (changing) threads, and glibc keeps the memory SuperLU frees in per-thread
# arenas: a 10 000-step run grew by ~0.27 MiB per step with everything on XLA's threads,
# while on one thread the resident memory stayed flat (1682.2 -> 1682.4 MiB over 900
# steps, measured). Solves run on the calling thread: what one allocates it frees before
# it returns, and the hop to the worker and back cost ~0.25 ms per solve (2D L-shape r4,
# eG(1), h = 0.1: 15.7-15.9 -> 14.3 ms per step, 6 solves a step; session 35).
# The thread starts with the first factorization (importing jaxvisco starts none).
@functools.lru_cache(maxsize=1)
def _worker():
    return concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="jaxvisco-superlu")


def _on_worker(fn):
    @functools.wraps(fn)
    def run(*args, **kwargs):
        return _worker().submit(fn, *args, **kwargs).result()

    return run


def _retract_all(extension, key, tokens):
    for t in list(tokens):
        extension.retract(key, t)


def _pattern(key):
    host = _REGISTRY.get(key)
    if host is None:
        raise RuntimeError(f"jaxvisco: no sparsity pattern with key {key} in this process (the compiled program "
                           "outlived its pattern); call jax.clear_caches() and run again.")
    return host


def _host_call(op, key, arg, src, dst):
    """What the FFI targets call (with the GIL): factor (op 0) the values in `src`
    keeping at least `arg` factorizations, and write the token to `dst`; or solve (op 1;
    op 2 transposed) with the token `arg` for the right-hand side `src` into `dst`.
    `src`, `dst`: memoryviews of XLA's buffers, valid during the call only."""
    host = _pattern(key)
    if op == 0:
        data = np.frombuffer(src, dtype=np.float64)
        np.frombuffer(dst, dtype=np.int64)[0] = _on_worker(host.factor)(data, retain=arg)
    else:
        b = np.frombuffer(src, dtype=np.float64)
        np.frombuffer(dst, dtype=np.float64)[:] = host.solve(arg, b, trans=op == 2)


def _factor_by_key(key, data, retain):
    return _pattern(key).factor(data, retain=retain)


if _hostlu is not None:
    _hostlu.set_callable(_host_call)
    jax.ffi.register_ffi_target("jaxvisco_lu_factor", _hostlu.factor_target(), platform="cpu")
    jax.ffi.register_ffi_target("jaxvisco_lu_solve", _hostlu.solve_target(), platform="cpu")


def lu_factor(host: HostLU, data, retain=RETAIN):
    """Factor the matrix with COO values `data`, keeping at least `retain` factorizations
    of the pattern alive; returns an integer token.

    The values carry no derivative (`stop_gradient`). The fallback path is a
    `pure_callback`, although factoring adds to the host store: JAX may drop a call
    whose token is unused, repeat one (a new token for equal factors) or move it, but
    never before its values exist nor after a solve that reads its token, and none of
    that changes a result. An `io_callback` would say "impure" honestly, but JAX cannot
    rematerialize effects: ``jax.checkpoint`` (the reverse-mode replay) refuses it
    (NotImplementedError: Effects not supported in partial-eval of checkpoint/remat)."""
    data = jax.lax.stop_gradient(data)
    out = jax.ShapeDtypeStruct((), jnp.int64)
    if backend() == "ffi":
        return jax.ffi.ffi_call("jaxvisco_lu_factor", out, vmap_method="sequential")(
            jnp.asarray(data, jnp.float64), key=np.int64(host.key), retain=np.int64(retain))
    return jax.pure_callback(_on_worker(functools.partial(_factor_by_key, host.key, retain=int(retain))), out, data,
                             vmap_method="sequential")


def lu_solve(host: HostLU, token, b, trans=False):
    """Solve with a factorization: $A^{-1} b$ (or $A^{-T} b$ with `trans`).

    A JAX primitive that is linear in `b`, with JVP, transpose (a solve with the
    transposed factors) and batching rules, so that a function built on it (the block
    solve of `_tangent`) can be linearized, transposed and vmapped: the implicit
    derivatives of a time step reuse the factorization in both directions.
    """
    return _lu_solve_p.bind(jnp.asarray(token, jnp.int64), b, key=int(host.key), trans=bool(trans))


def _lu_solve_impl(token, b, *, key, trans):
    out = jax.ShapeDtypeStruct(b.shape, b.dtype)
    if backend() == "ffi":
        return jax.ffi.ffi_call("jaxvisco_lu_solve", out, vmap_method="sequential")(
            token, b, key=np.int64(key), trans=np.int64(trans))
    # A solve only reads the store: a pure function of the token and b.
    return jax.pure_callback(functools.partial(_solve_by_key, key, trans=trans), out, token, b,
                             vmap_method="sequential")


def _solve_by_key(key, token, b, trans):
    return _pattern(key).solve(token, b, trans=trans)


def _lu_solve_jvp(primals, tangents, *, key, trans):
    token, b = primals
    out = _lu_solve_p.bind(token, b, key=key, trans=trans)
    db = tangents[1]
    if type(db) is ad.Zero:
        return out, ad.Zero.from_primal_value(out)
    return out, _lu_solve_p.bind(token, db, key=key, trans=trans)


def _lu_solve_transpose(ct, token, b, *, key, trans):
    if ad.is_undefined_primal(token):
        raise ValueError("lu_solve is not linear in the factorization token.")
    if type(ct) is ad.Zero:
        return None, ad.Zero(b.aval)
    return None, _lu_solve_p.bind(token, ct, key=key, trans=not trans)


def _lu_solve_batch(args, dims, *, key, trans):
    token, b = args
    td, bd = dims
    size = token.shape[td] if td is not None else b.shape[bd]
    token = jnp.broadcast_to(token, (size,)) if td is None else jnp.moveaxis(token, td, 0)
    b = jnp.broadcast_to(b, (size,) + b.shape) if bd is None else jnp.moveaxis(b, bd, 0)
    out = jax.lax.map(lambda tb: _lu_solve_p.bind(tb[0], tb[1], key=key, trans=trans), (token, b))
    return out, 0


_lu_solve_p = Primitive("jaxvisco_lu_solve")
_lu_solve_p.def_impl(_lu_solve_impl)
_lu_solve_p.def_abstract_eval(lambda token, b, **_: jax.core.ShapedArray(b.shape, b.dtype))
mlir.register_lowering(_lu_solve_p, mlir.lower_fun(_lu_solve_impl, multiple_results=False))
ad.primitive_jvps[_lu_solve_p] = _lu_solve_jvp
ad.primitive_transposes[_lu_solve_p] = _lu_solve_transpose
batching.primitive_batchers[_lu_solve_p] = _lu_solve_batch
