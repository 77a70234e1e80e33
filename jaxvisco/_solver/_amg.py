"""Aggregation multigrid for the condensed position block, in JAX.

The position block of a time element (`_tangent`) is a sparse matrix with a (k d) x (k d)
block per pair of mesh nodes that share an element. The direct path factors it on the
host (SuperLU): its fill grows superlinearly with the mesh, and every Krylov iteration
makes a host round trip. This module replaces that factorization with multigrid
cycles whose every operation is array arithmetic in the compiled program:

- **On the host, once per mesh** (`hierarchy`, cached per pattern like the LU pattern):
  only graphs. Nodes are aggregated by pyamg's standard aggregation on the node graph,
  then aggregates on the aggregate graph, until the coarsest matrix is small. Each level
  keeps its block pattern (rows sorted), where each fine block lands on the coarse
  pattern, and each node's aggregate and slot in it.
- **In JAX, at every tangent formation** (`build`): the near-null space of elasticity
  (rigid translations and rotations of each aggregate about its centroid, in the
  positions where the tangent is formed; one copy per time node), relaxed by a few
  Jacobi sweeps on A B = 0 and orthonormalized per aggregate (modified Gram–Schmidt in
  array operations: no LAPACK on stacks of small matrices), is the tentative
  prolongator T; the smoothed prolongator is P = (I - 4/(3 rho) D^{-1} A) T and the coarse
  operator the Galerkin product Pᵀ A P, formed block by block on the fixed patterns. The
  smoother is Chebyshev–Jacobi with the (k d) x (k d) node blocks (which hold the time
  coupling of the k nodes, inverted by `small_inv`); the coarsest level is a dense LU.
  The cycles read every operator row-padded (`_ell`: each node's blocks side by side,
  padded with a zero block), so a product is a gather and a reduction, never a scatter.
- `solve` applies `CYCLES` W-cycles (`cycle`, `GAMMA`) as a stationary iteration: a fixed linear map of its
  right-hand side, so it right-preconditions GMRES like the exact block solve did (no
  fill, no host call).
- **Precision**: `build` forms the operators in the tangent's float64 and stores them in
  float32 by default (`GMRES.multigrid_precision`); the cycles then run in float32 and
  `solve` returns float64. A block solve has to reduce the residual 50-fold (chord) or
  by `CYCLES` cycles' worth (GMRES), far above float32 rounding, and the cycles are bound by
  memory traffic, which halves: see `GMRES` for the measurements.

Held components are decoupled rows of the block (a scaled identity), so their modes are
zero in T: the smoother solves them exactly.

Why hand-written: pyamg builds hierarchies on the host with scipy matrices; we need the
numeric phase (coarse operators, smoother, cycle) inside jitted JAX programs, re-formed
whenever the tangent is, and no JAX library provides aggregation multigrid. pyamg does
the graph aggregation here.
"""

import contextlib
import contextvars
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from .._fem._tensor import small_inv

# Largest coarsest matrix (unknowns) solved by a dense LU.
MAX_COARSE = 1500
# Cycles per application of the preconditioner inside GMRES (`solve` without `rtol`): a
# Krylov vector costs a JVP of the step residual (3D L-shape hex8 r9, eG(1): 1.64 s,
# 2.7 residuals on this memory-first path) and a W-cycle 0.135 s, so a closer block solve
# pays. Krylov vectors per Newton iteration, hex8, eG(1), h = 0.1, `chord=0`, 3 steps
# (`benchmarks/results/scaling_chord0_s28.json`, `..._cycles6_s28.json`):
#   refinement        2     5     8     11    14 (1e6 unknowns)
#   4 cycles        2.67  3.11  3.78  3.89  4.11   (1.54x from r2 to r14)
#   6 cycles        2.22  2.22  2.56  2.60  2.64   (1.19x)
# Newton iterations per step 3 everywhere with 4 cycles, 3-3.67 with 6; Krylov vectors per
# step at r14 12.3 -> 9.7; the first call there (compile and 3 steps; the 4 cycles then
# unrolled, the 6 a loop) 630 -> 385 s. The fixed-step default steps end in chord
# iterations, whose block solve cycles to `CHORD_RTOL` instead (`solve(rtol=)`), so this
# count acts where Newton–Krylov iterations run: first steps that fail to contract, large
# or adaptive steps, the implicit derivative's solves. Earlier, with V-cycles (hex8 r4):
# 1 cycle 3297 ms/step (15.7 Krylov vectors/step), 4 cycles 1284 (2.0), 8 cycles 1475 (1.5).
CYCLES = 6
# The chord iterations' block solve (`_newton._chord`: no Krylov method around it, so it
# need not be a fixed linear map) cycles until the block residual fell by this factor,
# at most `MAX_CYCLES` times. A chord iteration contracts no better than its block
# solve, and `CYCLES` fixed cycles reduce the residual by rate^4: 0.03 at r4 (rate
# 0.40) but 0.11 at r8 (0.574), where the chord iterations hit their limit (10) every
# step and a Newton–Krylov iteration finished it. 3D L-shape hex8, eG(1), h = 0.1, 4 steps
# (r8) / 3 steps (r6), alternating runs, same machine state: r8 29.7 / 25.3 -> 26.2 /
# 20.9 s/step, chord 10/10/10 + 1 Newton (2 Krylov) per step -> 7/7/9 and none; r6
# 11.5 / 12.6 -> 11.4 / 10.2 s/step, chord 7/8 -> 6/7. 0.005 at r8: chord 6/7/9, 23.6 s/step.
CHORD_RTOL = 0.02
MAX_CYCLES = 16
# Degree of the Chebyshev–Jacobi smoother before and after the coarse correction
# (V-cycle rate on the 2D L-shape r4 / 3D r3, eG(1), h = 0.1: degree 2 0.68 / 0.62,
# 3 0.57 / 0.52, 4 0.50 / 0.40).
DEGREE = 3
# Cycles of the next level per coarse correction (`cycle`): 1 is a V-cycle, 2 a W-cycle.
# With V-cycles the rate grew with the depth of the hierarchy (3D L-shape hex8, eG(1),
# h = 0.1, MAX_COARSE 1500: r2 / r4 / r6 / r8 0.394 / 0.461 / 0.551 / 0.721), while the
# two-grid rate with a (near) exact level-1 solve stayed at 0.398 / 0.402 (r4 / r6): the
# inexact coarse solve was what degraded. W-cycles: 0.394 / 0.401 / 0.419 / 0.574; level 1
# is 20-30x smaller than level 0 (aggregates of 27 nodes), so it costs little more.
# A coarse level of more than `LARGE_LEVEL` nodes gets one cycle more: the W-cycle rate
# grew once level 1 was large. Float32 cycles, random right-hand side, standalone (same
# process), rate / ms per cycle with level 0 taking 2, 3 or 4 cycles of level 1:
#   hex8 r5 (3 levels, level 1: 792 nodes)     2: 0.437 / 80    3: 0.427 / 79
#   hex8 r8 (3 levels, 2 835 nodes)            2: 0.574 / 275   3: 0.467 / 294
#   hex8 r11 (4 levels, 6 912 nodes)           2: 0.601 / 518   3: 0.483 / 614   4: 0.431 / 750
# (more smoothing instead, degree 6 on the coarse levels: r8 0.458 / 339, r11 0.481 / 678).
# In the time loop (eG(1), h = 0.1, 3 steps, alternating runs) the chord iterations' block
# solves took 7.4 cycles on average at r8 with 2 and 5.8 with 3 (solve time -25 %,
# s/step 8.59 -> 7.58; as a loop 7.23, first call 63 -> 54 s); at r5 3 cycles took as many
# (5.1) and cost 20 % more per solve. Log-log slope from 12 000 to 1e6 unknowns of the
# steps that reuse the tangent 1.14 -> 1.10 (medians, `benchmarks/results/scaling_cpu_r14_s29.json`).
GAMMA = 2
LARGE_LEVEL = 2000
# Jacobi sweeps on A B = 0 that adapt the rigid modes to the block before aggregation
# (the mass term lifts them): rates 0.57 -> 0.47 (2D r4), 0.52 -> 0.44 (3D r3) with 4.
IMPROVE = 4
# Block products of the Galerkin operator formed at a time (`_block_products`).
PRODUCTS_PER_CHUNK = 1 << 16


# The hierarchy's index arrays as arguments of the program being traced (`arguments`):
# {(id(owner), name): traced array}, or None where they are read as constants.
_ARGUMENTS = contextvars.ContextVar("jaxvisco_multigrid_arguments", default=None)


class _Indexed:
    """Host index arrays that traced code reads through `ix`: the program's argument where
    `arguments` passes them in, else the host array (a constant of the program)."""

    def ix(self, name):
        subs = _ARGUMENTS.get()
        if subs is not None and (id(self), name) in subs:
            return subs[(id(self), name)]
        return jnp.asarray(self.index_arrays()[name])


class Level(_Indexed):
    """Host description of one level: its block pattern and its map to the next level."""

    def __init__(self, rows, cols, n):
        self.rows, self.cols, self.n = rows.astype(np.int32), cols.astype(np.int32), int(n)
        self.diag = _find(rows, cols, np.arange(n), np.arange(n), n)
        self.ell, self.ell_cols = _ell(self.rows, self.cols, n)
        self.agg = self.slot = self.members = None  # set by `_coarsen` (not on the coarsest level)
        self._index = (None, None)  # (PRODUCTS_PER_CHUNK, `index_arrays()`) of the last call

    @property
    def nnzb(self):
        return len(self.rows)

    def index_arrays(self):
        """The level's index arrays that traced code reads (`ix`), the block products'
        lists chunked as `_block_products` scans them (by `PRODUCTS_PER_CHUNK`)."""
        if self._index[0] != PRODUCTS_PER_CHUNK:
            names = ("rows", "cols", "diag", "ell", "ell_cols", "agg", "slot", "members", "p_rows", "p_diag",
                     "p_ell", "p_ell_cols", "r_ell", "r_ell_rows")
            out = {n: getattr(self, n) for n in names if getattr(self, n, None) is not None}
            if self.agg is not None:
                out |= _product_lists("z", np.arange(self.nnzb, dtype=np.int32), self.cols, self.z_target,
                                      len(self.p_rows))
                out |= _product_lists("ap", self.ap_a, self.ap_p, self.ap_t, self.ap_n)
                out |= _product_lists("c", self.c_p, self.c_s, self.c_t, self.next_nnzb)
            self._index = (PRODUCTS_PER_CHUNK, out)
        return self._index[1]


def _find(rows, cols, r, c, n):
    """Positions of the blocks (r, c) in the sorted pattern (rows, cols)."""
    key = rows.astype(np.int64) * n + cols
    want = np.asarray(r, np.int64) * n + c
    pos = np.searchsorted(key, want)
    assert np.all(key[pos] == want)
    return pos.astype(np.int32)


def _ell(rows, other, n):
    """Row-padded ("ELLPACK") layout of the blocks with rows `rows` (any order): for each
    of the n rows, the positions of its blocks in the list (n, w), padded with len(rows),
    which points at a zero block appended to the list, and the `other` index (column) of
    each (padding: 0)."""
    rows = np.asarray(rows)
    order = np.argsort(rows, kind="stable")
    counts = np.bincount(rows, minlength=n)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(rows)) - start[rows[order]]
    idx = np.full((n, max(int(counts.max(initial=0)), 1)), len(rows), np.int32)
    idx[rows[order], slot] = order
    return idx, np.append(np.asarray(other, np.int32), np.int32(0))[idx]


def _pattern(rows, cols, n):
    """Unique (row, col) pairs sorted by row then column, and the inverse map."""
    key = np.asarray(rows, np.int64) * n + np.asarray(cols, np.int64)
    uniq, inverse = np.unique(key, return_inverse=True)
    return (uniq // n), (uniq % n), inverse.astype(np.int32)


def _aggregate(level):
    """pyamg's standard aggregation on the level's graph; nodes it leaves out (no
    neighbours) become aggregates of their own."""
    from pyamg.aggregation.aggregate import standard_aggregation

    n = level.n
    off = level.rows != level.cols
    C = sp.csr_array((np.ones(off.sum()), (level.rows[off], level.cols[off])), shape=(n, n))
    agg_op, _ = standard_aggregation(C)
    agg_op = sp.csr_array(agg_op)
    agg = np.full(n, -1, np.int64)
    counts = np.diff(agg_op.indptr)
    agg[counts > 0] = agg_op.indices
    lone = np.flatnonzero(agg < 0)
    agg[lone] = agg_op.shape[1] + np.arange(len(lone))
    return agg, agg_op.shape[1] + len(lone)


def _ptr(rows, n):
    return np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))])


def _products(x_out, x_mid, y_ptr, y_cols):
    """Block products of X Y on fixed patterns: X's blocks (x_out, x_mid), Y's blocks in
    CSR (y_ptr, y_cols). Returns, per product, the X block, the Y block, and the output
    (row, col)."""
    counts = y_ptr[x_mid + 1] - y_ptr[x_mid]
    q = np.repeat(np.arange(len(x_mid)), counts)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    p = y_ptr[x_mid[q]] + np.arange(len(q)) - first[q]
    return q, p, x_out[q], y_cols[p]


def _coarsen(level):
    """Aggregate the level's nodes and work out, on the host, every block product that
    the smoothed-aggregation Galerkin operator $P^T A P$ needs, with
    $P = (I - \\omega D^{-1} A) T$: Z = A T on the pattern (i, agg(j)) (also P's pattern),
    then A P and Pᵀ (A P)."""
    agg, n_c = _aggregate(level)
    order = np.argsort(agg, kind="stable")
    sizes = np.bincount(agg, minlength=n_c)
    start = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    slot = np.empty(level.n, np.int64)
    slot[order] = np.arange(level.n) - start[agg[order]]
    members = np.full((n_c, sizes.max()), level.n, np.int64)  # padded with a dummy node
    members[agg, slot] = np.arange(level.n)
    i32 = lambda a: np.asarray(a, np.int32)  # noqa: E731
    level.agg, level.slot, level.members = i32(agg), i32(slot), i32(members)
    # P's pattern: Z = A T lands on (i, agg(j))
    zr, zc, level.z_target = _pattern(level.rows, agg[level.cols], n_c)
    level.p_rows, level.p_cols = i32(zr), i32(zc)
    level.p_diag = i32(_find(zr, zc, np.arange(level.n), agg, n_c))
    level.p_ell, level.p_ell_cols = _ell(zr, zc, level.n)  # prolongation: P's blocks by row
    level.r_ell, level.r_ell_rows = _ell(zc, zr, n_c)  # restriction: by column (P^T's rows)
    # A P: A's block (i, j) times P's blocks in row j
    q, p, r, c = _products(level.rows, level.cols, _ptr(zr, level.n), zc)
    apr, apc, t = _pattern(r, c, n_c)
    level.ap_a, level.ap_p, level.ap_t, level.ap_n = i32(q), i32(p), i32(t), len(apr)
    # P^T (A P): P's block (i, I) times (A P)'s blocks in row i
    q, p, r, c = _products(zc, zr, _ptr(apr, level.n), apc)
    cr, cc, t = _pattern(r, c, n_c)
    level.c_p, level.c_s, level.c_t = i32(q), i32(p), i32(t)
    level.next_nnzb = len(cr)
    return Level(cr, cc, n_c)


class Hierarchy(_Indexed):
    """The host part of the multigrid for one position-block pattern (`hierarchy`)."""

    def __init__(self, cells, k, n_nodes, dim, held, max_coarse=None):
        max_coarse = MAX_COARSE if max_coarse is None else max_coarse
        self.k, self.dim, self.b = k, dim, k * dim
        self.r = 3 if dim == 2 else 6  # rigid modes per time node
        self.m = k * self.r
        c = np.asarray(cells)
        n_en = c.shape[1]
        rows = np.broadcast_to(c[:, :, None], (len(c), n_en, n_en)).ravel()
        cols = np.broadcast_to(c[:, None, :], (len(c), n_en, n_en)).ravel()
        r, cc, self.element_map = _pattern(rows, cols, n_nodes)
        self.levels = [Level(r, cc, n_nodes)]
        while self.levels[-1].n * (self.b if len(self.levels) == 1 else self.m) > max_coarse:
            nxt = _coarsen(self.levels[-1])
            if nxt.n >= self.levels[-1].n:  # the graph stopped coarsening
                self.levels[-1].agg = None
                break
            self.levels.append(nxt)
        # held components: (node, component within the node's k*d block)
        self.held = held  # (n_nodes, dim) bool or None
        if held is not None:
            node, comp = np.nonzero(np.asarray(held))
            node = np.repeat(node[None], k, 0).ravel()
            comp = (np.arange(k)[:, None] * dim + comp[None]).ravel()
            self.held_block, self.held_pos = self.levels[0].diag[node], comp.astype(np.int32)
            self.free = np.tile(~np.asarray(held), (1, k)).astype(float)  # (n_nodes, k*d)

    def describe(self):
        return [dict(nodes=lv.n, blocks=lv.nnzb) for lv in self.levels]

    def index_arrays(self):
        """The hierarchy's own index arrays that traced code reads (`ix`)."""
        out = dict(element_map=self.element_map)
        if self.held is not None:
            out |= dict(held_block=self.held_block, held_pos=self.held_pos, free=self.free)
        return out

    def arguments(self):
        """Every index array of the hierarchy and its levels on the device, as the
        program argument that `arguments` passes in: {name: array}."""
        out = {k: jnp.asarray(v) for k, v in self.index_arrays().items()}
        for i, lv in enumerate(self.levels):
            out |= {f"L{i}.{k}": jnp.asarray(v) for k, v in lv.index_arrays().items()}
        return out


@contextlib.contextmanager
def arguments(hier, args):
    """Within this context, the traced code of `hier` reads its index arrays from `args`
    (`Hierarchy.arguments`, passed in as arguments of the program being traced) instead
    of embedding them as constants. `args` None: no change.

    Why: embedded, each use of an array is a constant of its own, copied through every
    stage of the compilation (the program, XLA's module, the executable). The time loop
    of the 3D L-shape hex8, eG(1): at r1 (the test) 114 354 -> 2 808 integer constant
    elements; at r6 (`benchmarks/loop_memory.py`) peak RSS after compiling 1440 -> 1127
    MB, lowering 6.4 -> 3.4 s, compiling 43.6 -> 36.3 s; a 5-step run at r8 (index arrays
    185 MB) peaked at 3422 MB against 3700 MB."""
    if args is None:
        yield
        return
    subs = {(id(hier), k): args[k] for k in hier.index_arrays()}
    for i, lv in enumerate(hier.levels):
        subs |= {(id(lv), k): args[f"L{i}.{k}"] for k in lv.index_arrays()}
    token = _ARGUMENTS.set(subs)
    try:
        yield
    finally:
        _ARGUMENTS.reset(token)


@functools.lru_cache(maxsize=16)
def _hierarchy(cells, k, n_nodes, dim, fixed, max_coarse):
    return Hierarchy(cells.array, k, n_nodes, dim, None if fixed is None else fixed.array, max_coarse)


def hierarchy(cells, k, n_nodes, dim, fixed=None) -> Hierarchy:
    """The (cached) host hierarchy of a mesh's position block: `cells`, `fixed` as the
    `StaticArray`s of the scene's discretization; coarsened until the coarsest matrix
    has at most `MAX_COARSE` unknowns (read at each call, so a test can lower it)."""
    return _hierarchy(cells, k, n_nodes, dim, fixed, MAX_COARSE)


def of_scene(k, scene) -> Hierarchy:
    """The hierarchy of the position block of `scene` for time elements of `k` nodes."""
    disc = scene.disc
    return hierarchy(disc.cells, k, disc.n_nodes, scene.dim, scene.fixed)


class Multigrid(eqx.Module):
    """The numeric multigrid of one tangent, its blocks row-padded (n, w, a, c) as its
    cycles read them (`_ell`, `_ell_apply`): per level the blocks of A; per level but the
    coarsest the inverted diagonal blocks (n, b, b) and the smoothed prolongator P, by
    rows (n, w, b, m: prolongation) and by columns (n_c, w, b, m: restriction); the LU
    of the coarsest matrix."""

    A: tuple
    Dinv: tuple
    P: tuple
    R: tuple
    rho: jax.Array  # estimated spectral radius of D^-1 A per level (the smoother's interval)
    lu: jax.Array
    piv: jax.Array


def _segment_sum(x, ids, n):
    return jax.ops.segment_sum(x, ids, num_segments=n)


def chunked(a, size, fill):
    """The host index array `a` (n, ...) padded with `fill` to a multiple of `size` rows
    and split into chunks (m, size, ...), for a `lax.scan` that adds each chunk into its
    carry (a `fill` beyond the output's last block is dropped by ``mode="drop"``)."""
    a = np.asarray(a)
    m = -(-len(a) // size)
    pad = np.full((m * size - len(a),) + a.shape[1:], fill, a.dtype)
    return np.concatenate([a, pad]).reshape((m, size) + a.shape[1:])


def _product_lists(name, xi, yi, target, n_out):
    """The index lists of one `_block_products` ({name}.x, .y, .target), chunked
    (m, `PRODUCTS_PER_CHUNK`) where they are longer than a chunk."""
    c = PRODUCTS_PER_CHUNK
    if len(xi) > c:
        xi, yi, target = chunked(xi, c, 0), chunked(yi, c, 0), chunked(target, c, n_out)
    return {f"{name}.x": np.asarray(xi, np.int32), f"{name}.y": np.asarray(yi, np.int32),
            f"{name}.target": np.asarray(target, np.int32)}


def _block_products(spec, X, Y, lv, name, n_out):
    """sum over t of einsum(spec, X[xi[t]], Y[yi[t]]) into output block target[t] (n_out
    blocks), the lists (xi, yi, target) the level's `name` (`_product_lists`); in chunks
    of `PRODUCTS_PER_CHUNK` (a `lax.scan` that adds into its carry), so that only one
    chunk's gathered blocks are alive at a time: the product lists grow with the mesh (A P
    of the 3D L-shape hex8 r4: 963 739 products, three 3 x 6 or 3 x 3 arrays of them at
    once, 330 MB)."""
    idx = tuple(lv.ix(f"{name}.{part}") for part in ("x", "y", "target"))
    if idx[0].ndim == 1:
        return _segment_sum(jnp.einsum(spec, X[idx[0]], Y[idx[1]]), idx[2], n_out)
    out_shape = jax.eval_shape(lambda a, b: jnp.einsum(spec, a, b), X[:1], Y[:1]).shape[1:]

    def add(out, chunk):
        a, b, t = chunk
        return out.at[t].add(jnp.einsum(spec, X[a], Y[b]), mode="drop"), None

    out, _ = jax.lax.scan(add, jnp.zeros((n_out,) + out_shape, X.dtype), idx)
    return out


def element_node_blocks(Ke):
    """Element blocks (ne, k, n_en, d, k, n_en, d) as node-pair blocks (ne n_en n_en, k d, k d),
    in the order of `Hierarchy.element_map`."""
    ne, k, n_en, d = Ke.shape[:4]
    return jnp.transpose(Ke, (0, 2, 5, 1, 3, 4, 6)).reshape(ne * n_en * n_en, k * d, k * d)


def add_held(hier: Hierarchy, A, held_value):
    """The node blocks A with the held components' diagonal value added."""
    if hier.held is not None:
        pos = hier.ix("held_pos")
        A = A.at[hier.ix("held_block"), pos, pos].add(held_value)
    return A


def _rigid_modes(hier, x, level):
    """Rigid-body modes of each node about its aggregate's centroid (n, k d, k r)."""
    n, d, k = level.n, hier.dim, hier.k
    agg = level.ix("agg")
    counts = _segment_sum(jnp.ones(n), agg, len(level.members))
    centre = _segment_sum(x, agg, len(level.members)) / counts[:, None]
    y = x - centre[agg]
    eye = jnp.broadcast_to(jnp.eye(d), (n, d, d))
    if d == 2:
        rot = jnp.stack([-y[:, 1], y[:, 0]], axis=1)[:, :, None]
    else:
        z = jnp.zeros(n)
        rot = jnp.stack([jnp.stack([z, -y[:, 2], y[:, 1]], 1), jnp.stack([y[:, 2], z, -y[:, 0]], 1),
                         jnp.stack([-y[:, 1], y[:, 0], z], 1)], axis=2)  # columns e_i x y
    Br = jnp.concatenate([eye, rot], axis=2)  # (n, d, r)
    B = jnp.einsum("JI,ndr->nJdIr", jnp.eye(k), Br).reshape(n, k * d, k * hier.r)
    if hier.held is not None:
        B = B * hier.ix("free")[:, :, None]
    return B


def _orthonormalize(X, tol=1e-10):
    """Modified Gram–Schmidt on each (rows, m) matrix of the stack X: Q, R with X = Q R;
    a column that depends on the previous ones (relative norm below `tol`) gets a zero
    column in Q and is flagged (`dead`)."""
    m = X.shape[-1]
    scale = jnp.sqrt(jnp.sum(X**2, axis=-2))  # (s, m)
    Q, R, dead = [], [], []
    for j in range(m):
        v = X[..., j]
        r = []
        for q in Q:
            c = jnp.sum(q * v, axis=-1)
            v = v - c[..., None] * q
            r.append(c)
        nv = jnp.sqrt(jnp.sum(v**2, axis=-1))
        ok = nv > tol * jnp.maximum(scale[..., j], 1e-300)
        Q.append(jnp.where(ok[..., None], v / jnp.where(ok, nv, 1.0)[..., None], 0.0))
        R.append(jnp.stack(r + [jnp.where(ok, nv, 0.0)] + [jnp.zeros_like(nv)] * (m - j - 1), axis=-1))
        dead.append(~ok)
    return jnp.stack(Q, -1), jnp.stack(R, -1), jnp.stack(dead, -1)  # R[..., i, j]


def _to_ell(blocks, idx):
    """Blocks (nnz, a, c) in the row-padded layout (n, w, a, c) of `idx` (`_ell`)."""
    padded = jnp.concatenate([blocks, jnp.zeros((1,) + blocks.shape[1:], blocks.dtype)])
    return padded[jnp.asarray(idx)]


def _ell_apply(E, cols, x):
    """Row-padded blocks E (n, w, a, c) with columns `cols` (n, w) times x (N, c): (n, a).

    Why this layout: a gather and a reduction over each row's blocks, no scatter. With
    jaxvisco's XLA options (`_config`) on the 3D L-shape hex8 r4 (214 933 blocks of
    3 x 3, eG(1); 10 products in a jitted loop, medians): 1.0 ms per product, where the
    (nnzb, b, b) blocks with a sorted `segment_sum` took 3.3 ms and the component-major
    layout (a, c, n, w) 1.8 ms (XLA's defaults: 5.3 / 5.3 / 1.85 ms)."""
    return jnp.sum(E * x[jnp.asarray(cols)][:, :, None, :], axis=(1, 3))


def _restrict(R, rows, r):
    """Pᵀ r from P's blocks by column R (n_c, w, b, m) with their rows `rows`: (n_c, m)."""
    return jnp.sum(R * r[jnp.asarray(rows)][:, :, :, None], axis=(1, 2))


def _dmul(Dinv, r):
    """The inverted diagonal blocks (n, b, b) times r (n, b)."""
    return jnp.sum(Dinv * r[:, None, :], axis=-1)


def block_size(mg: Multigrid, level=0):
    """Unknowns per node of a level (k d on the finest, k r on the coarser ones)."""
    return mg.A[level].shape[-1]


def prolongator_blocks(hier: Hierarchy, mg: Multigrid, level=0):
    """P's blocks (n_p, b, m) in the order of its pattern (`Level.p_rows`, `p_cols`)."""
    lv = hier.levels[level]
    r, w = np.nonzero(lv.p_ell < len(lv.p_rows))
    order = np.argsort(lv.p_ell[r, w])
    return mg.P[level][r[order], w[order]]


def _spectral_radius(lv, E, Dinv, iterations=40):
    """Power-iteration estimate of the spectral radius of D^{-1} A (the Chebyshev
    smoother's interval ends at 1.1 times it). Measured on the 2D L-shape (refinement 16,
    eG(1), h = 0.1): 12 iterations gave 2.12 where 300 gave 2.55, and the V-cycle
    diverged; 50 gave 2.52. The row-sum bound (guaranteed, 3.43 there) kept it stable but
    cost 1.4-1.6x the Krylov vectors (2D r4, r16; 3D r2, r4)."""
    v = jnp.cos(jnp.arange(lv.n * E.shape[-1], dtype=float) * 0.618).reshape(lv.n, -1) + 1.0

    def step(_, v):
        w = _dmul(Dinv, _ell_apply(E, lv.ix("ell_cols"), v))
        return w / jnp.linalg.norm(w)

    v = jax.lax.fori_loop(0, iterations, step, v / jnp.linalg.norm(v))
    return jnp.linalg.norm(_dmul(Dinv, _ell_apply(E, lv.ix("ell_cols"), v)))


def build(hier: Hierarchy, A0, x, dtype=np.float32) -> Multigrid:
    """The multigrid of the position block with node blocks `A0` (`_tangent._multigrid_blocks`), for
    the nodal positions `x` (n_nodes, d) where the tangent is formed: formed in the
    precision of `A0`, its operators stored in `dtype` (the cycles' arithmetic;
    `GMRES.multigrid_precision`)."""
    E, Dinv, P, R, rhos = [], [], [], [], []
    Al, B = A0, None
    for lv, nxt in zip(hier.levels[:-1], hier.levels[1:]):
        El = _to_ell(Al, lv.ix("ell"))
        Dl = jax.vmap(small_inv)(Al[lv.ix("diag")])  # (n, b, b)
        rho = _spectral_radius(lv, El, Dl)
        E.append(El)
        Dinv.append(Dl)
        rhos.append(rho)
        if B is None:
            B = _rigid_modes(hier, x, lv)
        for _ in range(IMPROVE):  # relax A B = 0 from the rigid modes (pyamg's improve_candidates)
            # one mode at a time: all at once gathers (m, n, w, b) (3D hex8 r8: 243 MB)
            AB = jnp.moveaxis(jax.lax.map(lambda c: _ell_apply(El, lv.ix("ell_cols"), c), jnp.moveaxis(B, 2, 0)), 0, 2)
            B = B - (1.0 / rho) * jnp.einsum("nij,njm->nim", Dl, AB)
        b, m = B.shape[1:]
        pad = jnp.concatenate([B, jnp.zeros((1, b, m))])[lv.ix("members")]  # (n_c, s, b, m)
        n_c, s = lv.members.shape
        Q, Rq, dead = _orthonormalize(pad.reshape(n_c, s * b, m))
        T = Q.reshape(n_c, s, b, m)[lv.ix("agg"), lv.ix("slot")]  # (n, b, m)
        # smoothed prolongator P = (I - w D^-1 A) T, w = 4 / (3 rho(D^-1 A))
        Z = _block_products("nbc,ncm->nbm", Al, T, lv, "z", len(lv.p_rows))
        Pl = -(4.0 / (3.0 * rho)) * jnp.einsum("nbc,ncm->nbm", Dl[lv.ix("p_rows")], Z)
        Pl = Pl.at[lv.ix("p_diag")].add(T)
        P.append(_to_ell(Pl, lv.ix("p_ell")))
        R.append(_to_ell(Pl, lv.ix("r_ell")))
        AP = _block_products("nbc,ncm->nbm", Al, Pl, lv, "ap", lv.ap_n)
        Ac = _block_products("nbm,nbp->nmp", Pl, AP, lv, "c", nxt.nnzb)
        # a mode an aggregate cannot carry (two nodes cannot turn about their axis)
        Al = Ac.at[nxt.ix("diag")].add(jax.vmap(jnp.diag)(dead.astype(Ac.dtype)))
        B = Rq  # the coarse nodes' modes: X = Q R, so mode j is column j of R (m, m)
    last = hier.levels[-1]
    E.append(_to_ell(Al, last.ix("ell")))
    bl = Al.shape[-1]
    dense = jnp.zeros((last.n, bl, last.n, bl)).at[last.ix("rows"), :, last.ix("cols"), :].add(Al)
    lu, piv = jax.scipy.linalg.lu_factor(dense.reshape(last.n * bl, last.n * bl))
    mg = Multigrid(tuple(E), tuple(Dinv), tuple(P), tuple(R), jnp.stack(rhos) if rhos else jnp.zeros(0), lu, piv)
    return jax.tree_util.tree_map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, mg)


def matvec(hier: Hierarchy, mg: Multigrid, x, level=0):
    """The level's matrix times x (n, b)."""
    return _ell_apply(mg.A[level], hier.levels[level].ix("ell_cols"), x)


def _chebyshev(lv, A, Dinv, rho, rhs, x):
    """`DEGREE` steps of Chebyshev iteration for D^{-1} A x = D^{-1} rhs on the interval
    [rho / 30, 1.1 rho] (rho: the estimated spectral radius of D^{-1} A), from x; x = None
    means zero. A fixed polynomial in D^{-1} A: a linear map of (rhs, x)."""
    hi, lo = 1.1 * rho, rho / 30.0
    theta, delta = 0.5 * (hi + lo), 0.5 * (hi - lo)
    sigma = theta / delta
    cols = lv.ix("ell_cols")
    res = lambda x: _dmul(Dinv, rhs if x is None else rhs - _ell_apply(A, cols, x))  # noqa: E731
    r = res(x)
    d = r / theta
    x = d if x is None else x + d
    rho0 = 1.0 / sigma
    for _ in range(DEGREE - 1):
        r = res(x)
        rho1 = 1.0 / (2.0 * sigma - rho0)
        d = rho1 * rho0 * d + (2.0 * rho1 / delta) * r
        x = x + d
        rho0 = rho1
    return x


def cycle(hier: Hierarchy, mg: Multigrid, rhs, level=0):
    """One multigrid cycle for A x = rhs, from x = 0; `rhs` (n, b) at the level's nodes:
    Chebyshev–Jacobi smoothing before and after the coarse correction, which takes
    `GAMMA` cycles of the next level (one more where it has more than `LARGE_LEVEL`
    nodes, as a loop; one where it is the coarsest: its LU is exact). A fixed linear map
    of `rhs`."""
    lv = hier.levels[level]
    if level == len(hier.levels) - 1:
        sol = jax.scipy.linalg.lu_solve((mg.lu, mg.piv), rhs.reshape(-1))
        return sol.reshape(rhs.shape)
    A, Dinv, rho = mg.A[level], mg.Dinv[level], mg.rho[level]
    x = _chebyshev(lv, A, Dinv, rho, rhs, None)
    rc = _restrict(mg.R[level], lv.ix("r_ell_rows"), rhs - _ell_apply(A, lv.ix("ell_cols"), x))
    nxt = hier.levels[level + 1]
    gamma = 1 if level + 2 == len(hier.levels) else GAMMA + int(nxt.n > LARGE_LEVEL)
    xc = _cycles(hier, mg, rc, gamma, level + 1, loop=gamma > 2)
    x = x + _ell_apply(mg.P[level], lv.ix("p_ell_cols"), xc)
    return _chebyshev(lv, A, Dinv, rho, rhs, x)


def _cycles(hier: Hierarchy, mg: Multigrid, rhs, n, level=0, loop=False):
    """`n` cycles of x <- x + C(rhs - A x) at `level` from x = 0: a fixed linear map of
    `rhs`. Unrolled (the coarse corrections of `cycle`: n = `GAMMA` or 1), or with `loop`
    (`solve`'s `CYCLES` at the finest level, a large level's `GAMMA` + 1) the first cycle
    and then a `fori_loop` of the others: traced once, and with static bounds a scan, so
    still transposable.
    Unrolled, every cycle is another copy of the whole W-cycle in the compiled program;
    as a loop the 3D hex8 r4 block solve (four cycles) measured 8 % slower (236 vs 216 ms
    median), which only Newton–Krylov iterations pay now that the chord iterations cycle
    to a tolerance."""
    x = cycle(hier, mg, rhs, level)
    more = lambda _, x: x + cycle(hier, mg, rhs - matvec(hier, mg, x, level), level)  # noqa: E731
    if loop:
        return jax.lax.fori_loop(0, n - 1, more, x)
    for i in range(n - 1):
        x = more(i, x)
    return x


def solve(hier: Hierarchy, mg: Multigrid, rhs, cycles=None, rtol=None):
    """`cycles` cycles (default `CYCLES`) of x <- x + W(rhs - A x) from x = 0: a fixed
    linear map of `rhs`, so it preconditions GMRES like one cycle, closer to A^{-1}.

    With `rtol`, cycles go on until |rhs - A x| <= rtol |rhs| (2-norm) or `cycles`
    (default `MAX_CYCLES`) were taken: no longer a fixed linear map (not for GMRES).

    The cycles run in the multigrid's precision (`build(dtype=)`); x is returned in
    that of `rhs`."""
    out = rhs.dtype
    rhs = rhs.astype(mg.A[0].dtype)
    if rtol is None:
        return _cycles(hier, mg, rhs, CYCLES if cycles is None else cycles, loop=True).astype(out)
    bound = rtol * jnp.linalg.norm(rhs)

    def body(c):
        x, r, i = c
        x = x + cycle(hier, mg, r)
        return x, rhs - matvec(hier, mg, x), i + 1

    init = (jnp.zeros_like(rhs), rhs, jnp.asarray(0))
    cycles = MAX_CYCLES if cycles is None else cycles
    x, _, _ = jax.lax.while_loop(lambda c: (jnp.linalg.norm(c[1]) > bound) & (c[2] < cycles), body, init)
    return x.astype(out)
