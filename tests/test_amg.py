"""The multigrid path of the position block (`GMRES(preconditioner="amg")`, `_solver._amg`).

- The multigrid cycle alone, on the assembled position block of the 3D L-shape at two
  refinements: as a stationary iteration it reduces the residual by a fixed factor per
  cycle, and the factor does not grow from the coarser to the finer mesh beyond a small
  margin.
- Its building blocks: the Galerkin coarse block equals Pᵀ A P formed densely, and the
  rigid-body modes lie in the range of the tentative prolongator; assembled in passes
  and chunks (as on large meshes), the multigrid equals the one-pass form.
- A run on the multigrid path ends where the direct (host LU) path does, to the Newton
  tolerance: 2D and 3D (hex8, tet4, hex20), free flight and held nodes, eG(1) and eG(2).
- The compiled time loop takes the hierarchy's index arrays as arguments, not as
  constants, and takes the same steps as with them as constants.
- Reverse-mode gradients through a run on the multigrid path (the implicit step
  derivative solved by GMRES with the multigrid, transposed) equal central finite
  differences.

The meshes here are small, so `MAX_COARSE` is lowered to force several levels.
"""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import capture_time_loop

import jaxvisco as jv
from jaxvisco._solver import _amg, _tangent
from jaxvisco._time_element._step import make_context, predictor


def _scene(dim, refinement, element=None, held=False):
    mesh = jv.lshape_mesh(dim=dim, refinement=refinement, cell_type=element)
    nh = jv.NeoHooke(lam=30000.0, mu=7500.0)
    material = jv.ReeseGovindjee(nh, nh, eta_dev=50000.0, eta_vol=10000.0)
    X = np.asarray(mesh.points)
    w = 0.6 * np.stack([-X[:, 1], X[:, 0]], axis=-1)
    v0 = np.concatenate([w, np.zeros((len(X), 1))], axis=1) if dim == 3 else w
    v0 = v0 + np.eye(dim)[0] * 6.0
    kw = dict(fixed=np.broadcast_to((X[:, 1] < 1e-9)[:, None], X.shape)) if held else {}
    return jv.Scene(mesh, material, 8.93, velocities=v0, mass="consistent", **kw)


def _multigrid(scene, scheme, h=0.1, dtype=np.float64):
    """The multigrid of the position block at the predictor of the first step; in double
    precision unless asked (the algebra's identities below hold to float64 rounding)."""
    ctx = make_context(scene, scene.initial_state(), 0.0, h)
    U = predictor(scheme, scene, ctx, scene.v0)
    hier = _amg.hierarchy(scene.disc.cells, scheme.k, scene.disc.n_nodes, scene.dim, scene.fixed)
    tan = jax.jit(lambda c, u: _tangent.form_tangent(scheme, scene, c, u, preconditioner="amg", block_dtype=dtype))(ctx, U)
    return hier, tan.mg


def _cycle_rate(scene, scheme, cycles=10, built=None):
    """Residual reduction per cycle of x <- x + C(b - A x), over the last 4 cycles, in the
    multigrid's precision; `built`: its (hierarchy, multigrid), if formed already."""
    hier, mg = _multigrid(scene, scheme) if built is None else built
    dtype = mg.A[0].dtype
    b = jax.random.normal(jax.random.PRNGKey(0), (scene.disc.n_nodes, scheme.k * scene.dim)).astype(dtype)
    if hier.held is not None:
        b = b * hier.free.astype(dtype)

    @jax.jit
    def run(b):
        def step(x, _):
            r = b - _amg.matvec(hier, mg, x)
            return x + _amg.cycle(hier, mg, r), jnp.linalg.norm(r)

        _, norms = jax.lax.scan(step, jnp.zeros_like(b), None, length=cycles)
        return norms

    norms = np.asarray(run(b))
    return float((norms[-1] / norms[-5]) ** 0.25), len(hier.levels)


@pytest.mark.timeout(600)
def test_cycle_contracts_independently_of_refinement(monkeypatch):
    """3D L-shape hex8, refinements 1 and 2, three levels each, W-cycles (`_amg.GAMMA`).
    (With V-cycles the 2D rate grew from 3 to 4 levels: r4 / r8 / r16 0.47 / 0.76 / 0.76.)"""
    monkeypatch.setattr(_amg, "MAX_COARSE", 60)
    rates = []
    for r in (1, 2):
        rate, levels = _cycle_rate(_scene(3, r), jv.eG(1))
        assert levels >= 3, levels
        rates.append(rate)
    assert max(rates) < 0.6, rates
    assert rates[1] < rates[0] + 0.1, rates


@pytest.mark.timeout(300)
def test_a_large_coarse_level_takes_one_cycle_more(monkeypatch):
    """A coarse level of more than `_amg.LARGE_LEVEL` nodes gets `GAMMA` + 1 cycles per
    coarse correction, as a loop: the same map as those cycles unrolled, contracting faster
    than with `GAMMA` (here barely: 0.3883 -> 0.3879, level 1 has 81 nodes; see `_amg.GAMMA`
    for large levels), and the preconditioner stays a fixed linear map that
    `jax.linear_transpose` transposes (GMRES and the implicit derivative need both)."""
    monkeypatch.setattr(_amg, "MAX_COARSE", 60)
    scene = _scene(3, 2)
    hier, mg = _multigrid(scene, jv.eG(1))
    assert len(hier.levels) >= 3
    rates = {}
    for large in (10**9, 0):
        monkeypatch.setattr(_amg, "LARGE_LEVEL", large)
        rates[large] = _cycle_rate(scene, jv.eG(1), built=(hier, mg))[0]
    assert rates[0] < rates[10**9], rates
    x, y = jax.random.normal(jax.random.PRNGKey(2), (2, scene.disc.n_nodes, scene.dim))
    solve = lambda r: _amg.solve(hier, mg, r)  # noqa: E731
    S = jax.jit(solve)
    Sx = S(x)
    np.testing.assert_allclose(np.asarray(S(x + 2.0 * y)), np.asarray(Sx + 2.0 * S(y)), rtol=0,
                               atol=1e-12 * float(jnp.abs(Sx).max()))
    (St_y,) = jax.jit(jax.linear_transpose(solve, x))(y)
    np.testing.assert_allclose(float(jnp.vdot(St_y, x)), float(jnp.vdot(y, Sx)), rtol=1e-10)
    looped = jax.jit(lambda r: _amg.cycle(hier, mg, r))(x)  # LARGE_LEVEL = 0: GAMMA + 1 cycles as a loop
    monkeypatch.setattr(_amg, "LARGE_LEVEL", 10**9)
    monkeypatch.setattr(_amg, "GAMMA", _amg.GAMMA + 1)
    unrolled = jax.jit(lambda r: _amg.cycle(hier, mg, r))(x)
    np.testing.assert_allclose(np.asarray(looped), np.asarray(unrolled), rtol=0, atol=1e-12 * float(jnp.abs(unrolled).max()))


@pytest.mark.timeout(300)
def test_block_solve_to_a_tolerance(monkeypatch):
    """`_amg.solve(rtol=)` (the chord iterations' block solve) takes the fewest cycles
    that reach the tolerance: it equals the fixed solve with that many cycles, whose one
    cycle fewer misses it; `cycles` caps it."""
    monkeypatch.setattr(_amg, "MAX_COARSE", 60)
    scene = _scene(3, 2)
    hier, mg = _multigrid(scene, jv.eG(1))
    assert len(hier.levels) >= 3
    b = jax.random.normal(jax.random.PRNGKey(1), (scene.disc.n_nodes, scene.dim))
    rel = lambda x: float(jnp.linalg.norm(b - _amg.matvec(hier, mg, x)) / jnp.linalg.norm(b))  # noqa: E731
    fixed = jax.jit(lambda n: _amg.solve(hier, mg, b, cycles=n), static_argnums=0)
    for rtol in (3e-2, 1e-6):
        x = jax.jit(lambda: _amg.solve(hier, mg, b, rtol=rtol))()
        assert rel(x) <= rtol
        n = next(n for n in range(1, _amg.MAX_CYCLES + 1) if rel(fixed(n)) <= rtol)
        assert n >= 2 and rel(fixed(n - 1)) > rtol
        np.testing.assert_allclose(np.asarray(x), np.asarray(fixed(n)), rtol=0, atol=1e-12 * np.abs(np.asarray(x)).max())
    capped = jax.jit(lambda: _amg.solve(hier, mg, b, cycles=2, rtol=1e-12))()
    np.testing.assert_allclose(np.asarray(capped), np.asarray(fixed(2)), rtol=0, atol=1e-12 * np.abs(np.asarray(capped)).max())


@pytest.mark.timeout(300)
def test_galerkin_blocks_and_rigid_modes(monkeypatch):
    monkeypatch.setattr(_amg, "MAX_COARSE", 40)
    scene = _scene(2, 2)
    hier, mg = _multigrid(scene, jv.eG(1))
    lv, n, b = hier.levels[0], scene.disc.n_nodes, 2

    def dense(level):
        size = hier.levels[level].n * _amg.block_size(mg, level)
        E = jnp.eye(size).reshape(size, hier.levels[level].n, -1)
        return np.asarray(jax.vmap(lambda e: _amg.matvec(hier, mg, e, level))(E).reshape(size, size)).T

    A, Ac = dense(0), dense(1)
    Pb = np.asarray(_amg.prolongator_blocks(hier, mg, 0))
    m = Pb.shape[-1]
    P = np.zeros((n * b, len(lv.members) * m))
    for blk, (i, I) in enumerate(zip(lv.p_rows, lv.p_cols)):
        P[i * b:(i + 1) * b, I * m:(I + 1) * m] += Pb[blk]
    np.testing.assert_allclose(Ac, P.T @ A @ P, rtol=0, atol=1e-10 * np.abs(Ac).max())
    # P = (I - w D^-1 A) T keeps what A maps to nearly zero: the rigid modes of the mesh
    # lie in the range of P up to the smoothing of their (small) image under A.
    X = np.asarray(scene.mesh.points)
    B = np.zeros((n, 2, 3))
    B[:, 0, 0] = B[:, 1, 1] = 1.0
    B[:, 0, 2], B[:, 1, 2] = -X[:, 1], X[:, 0]
    B = B.reshape(n * b, 3)
    coef = np.linalg.lstsq(P, B, rcond=None)[0]
    assert np.abs(P @ coef - B).max() < 0.05 * np.abs(B).max()


@pytest.mark.timeout(300)
def test_chunked_assembly_equals_one_pass(monkeypatch):
    """How large meshes form the multigrid equals the one-pass forms, held nodes and eG(2)
    included: the node blocks and point sensitivities from passes of elements
    (`_tangent._multigrid_blocks`), and the Galerkin products in chunks (`_amg.build`)
    from the same node blocks. (Each identity on its own: passes of points batch the
    point Jacobians differently, which moves them by rounding, and the coarse levels
    amplify that.)"""
    monkeypatch.setattr(_amg, "MAX_COARSE", 40)
    scene, scheme = _scene(3, 1, "hex8", held=True), jv.eG(2)
    ctx = make_context(scene, scene.initial_state(), 0.0, 0.1)
    U = predictor(scheme, scene, ctx, scene.v0)
    hier = _amg.hierarchy(scene.disc.cells, scheme.k, scene.disc.n_nodes, scene.dim, scene.fixed)

    def blocks(ctx, U):
        _, F, G = _tangent.nodal_fields(scheme, scene, ctx, U)
        point = lambda mat, f, g: _tangent._point_tangent(scheme, mat, ctx.h, f, g)  # noqa: E731
        return _tangent._multigrid_blocks(scheme, scene, ctx, F, G, hier, point)

    def same(one, other):
        for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(other)):
            np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=1e-12 * np.abs(np.asarray(a)).max())

    # (a new function per trace: the pass sizes are read when it is traced)
    one = jax.jit(lambda c, u: blocks(c, u))(ctx, U)
    monkeypatch.setattr(_tangent, "ELEMENTS_PER_PASS", 50)  # 117 elements: 3 passes, the last overlapping
    same(one, jax.jit(lambda c, u: blocks(c, u))(ctx, U))
    build = lambda A0: _amg.build(hier, A0, ctx.state.x, np.float64)  # noqa: E731
    whole = jax.jit(lambda a: build(a))(one[0])
    monkeypatch.setattr(_amg, "PRODUCTS_PER_CHUNK", 1000)
    same(whole, jax.jit(lambda a: build(a))(one[0]))


# In CI: 2D free and held (eG(2)), 3D free (tet4) and held (hex8, hex20); the eG(1) 2D
# cases and the free hex8 are kept for `-m slow` (~50 s of the suite's time).
_SLOW = pytest.mark.slow
CASES = [
    pytest.param(2, 2, None, False, 1, marks=_SLOW), pytest.param(2, 2, None, True, 1, marks=_SLOW),
    (2, 2, None, False, 2), (2, 2, None, True, 2),
    pytest.param(3, 1, "hex8", False, 1, marks=_SLOW), (3, 1, "hex8", True, 1), (3, 1, "tet4", False, 1),
    (3, 1, "hex20", True, 1),
]
_IDS = [(c.values if hasattr(c, "values") else c) for c in CASES]


@pytest.mark.timeout(900)
@pytest.mark.parametrize("dim,r,element,held,k", CASES,
                         ids=[f"{d}D-{e or 'quad4'}-{'held' if h else 'free'}-eG({k})" for d, _, e, h, k in _IDS])
def test_multigrid_path_matches_direct(dim, r, element, held, k, monkeypatch):
    monkeypatch.setattr(_amg, "MAX_COARSE", 40)
    scene = _scene(dim, r, element, held)
    steps, h = 4, 0.1
    ends = {}
    for pc in ("lu", "amg"):
        solver = jv.NewtonKrylov(linear_solver=jv.GMRES(preconditioner=pc, refresh_after=30))
        sol = jv.simulate(scene, jv.eG(k), t1=steps * h, dt0=h, root_finder=solver, saveat=jv.SaveAt(every=steps))
        assert sol.status == "done", sol.status
        ends[pc] = sol
    hier = _amg.hierarchy(scene.disc.cells, k, scene.disc.n_nodes, dim, scene.fixed)
    assert len(hier.levels) >= 2
    scale = np.abs(np.asarray(ends["lu"].x[-1])).max()
    np.testing.assert_allclose(np.asarray(ends["amg"].x[-1]), np.asarray(ends["lu"].x[-1]), rtol=0, atol=1e-8 * scale)
    p_scale = np.abs(np.asarray(ends["lu"].p[-1])).max()
    np.testing.assert_allclose(np.asarray(ends["amg"].p[-1]), np.asarray(ends["lu"].p[-1]), rtol=0,
                               atol=1e-7 * p_scale)
    # the run on the multigrid path keeps eG's energy balance and momenta like the direct one
    sol = ends["amg"]
    H, D, W = (np.asarray(a) for a in (sol.energy, sol.dissipated, sol.external_work))
    assert abs((H[-1] + D[-1] - W[-1]) - H[0]) < 1e-8 * abs(H[0])
    if not held:
        L = np.asarray(sol.angular_momentum)
        assert np.abs(L[-1] - L[0]).max() < 1e-8 * np.abs(L[0]).max()


@pytest.mark.timeout(600)
def test_chord_iterations_solve_the_block_to_their_tolerance(monkeypatch):
    """The chord iterations on the multigrid path solve the position block to
    `_amg.CHORD_RTOL`: made tight, they take the same steps as on the exact host LU
    (same chord and Newton counts once a tangent is stored, same end state); with one
    fixed cycle they need more. The first step differs by design: on the multigrid path
    it forms its tangent at the predictor and converges by chord iterations alone, where
    the LU path takes Newton–Krylov iterations (which form the tangent at the same point)."""
    monkeypatch.setattr(_amg, "MAX_COARSE", 40)
    # `CHORD_RTOL` is read when the loop is traced: no program from memory or from disk
    monkeypatch.setenv("JAXVISCO_EXPORT", "off")
    scene = _scene(2, 2)
    steps, h = 4, 0.1

    def run(pc):
        jax.clear_caches()
        # double: float32 cycles cannot solve the block to 1e-10 (`multigrid_precision`)
        solver = jv.NewtonKrylov(linear_solver=jv.GMRES(preconditioner=pc, refresh_after=30,
                                                        multigrid_precision="double"))
        sol = jv.simulate(scene, jv.eG(1), t1=steps * h, dt0=h, root_finder=solver, saveat=jv.SaveAt(every=steps))
        assert sol.status == "done", sol.status
        return sol

    lu = run("lu")
    monkeypatch.setattr(_amg, "CHORD_RTOL", 1e-10)
    monkeypatch.setattr(_amg, "MAX_CYCLES", 60)
    tight = run("amg")
    np.testing.assert_array_equal(np.asarray(tight.chord_iterations)[1:], np.asarray(lu.chord_iterations)[1:])
    np.testing.assert_array_equal(np.asarray(tight.newton_iterations)[1:], np.asarray(lu.newton_iterations)[1:])
    assert np.asarray(lu.newton_iterations)[0] > 0 and np.asarray(lu.chord_iterations)[0] == 0
    assert np.asarray(tight.newton_iterations)[0] == 0 and np.asarray(tight.chord_iterations)[0] > 0
    scale = np.abs(np.asarray(lu.x[-1])).max()
    np.testing.assert_allclose(np.asarray(tight.x[-1]), np.asarray(lu.x[-1]), rtol=0, atol=1e-8 * scale)
    monkeypatch.setattr(_amg, "CHORD_RTOL", 0.9)  # one cycle (its rate is ~0.4)
    loose = run("amg")
    assert np.sum(loose.chord_iterations) + 5 * np.sum(loose.newton_iterations) > \
        np.sum(tight.chord_iterations) + 5 * np.sum(tight.newton_iterations)


@pytest.mark.timeout(900)
def test_gradient_on_the_multigrid_path_matches_finite_differences(monkeypatch):
    """3D hex8 with held nodes, 4 steps of eG(1): d loss / d (log eta_dev, log eta_vol,
    velocity scale) by reverse mode against fourth-order central differences (eps = 1e-2,
    truncation ~1e-8; the loss varies over O(1) in these parameters)."""
    monkeypatch.setattr(_amg, "MAX_COARSE", 40)
    scene = _scene(3, 1, "hex8", held=True)
    solver = jv.NewtonKrylov(rtol=1e-12, linear_solver=jv.GMRES(preconditioner="amg"))

    def loss(theta):
        s = eqx.tree_at(lambda s: (s.material.eta_dev, s.material.eta_vol, s.v0), scene,
                        (jnp.exp(theta[0]), jnp.exp(theta[1]), theta[2] * scene.v0))
        sol = jv.simulate(s, jv.eG(1), t1=0.4, dt0=0.1, root_finder=solver)
        return sol.dissipated[-1] + sol.free_energy[-1] + 1e-3 * jnp.mean((sol.x[-1] - scene.x0) ** 2)

    theta = jnp.array([jnp.log(scene.material.eta_dev), jnp.log(scene.material.eta_vol), 1.0])
    g = np.asarray(eqx.filter_jit(jax.grad(loss))(theta))
    eps = 1e-2
    f = np.array([[float(loss(theta + s * eps * jnp.eye(3)[i])) for s in (1.0, -1.0, 2.0, -2.0)] for i in range(3)])
    fd = (8 * (f[:, 0] - f[:, 1]) - (f[:, 2] - f[:, 3])) / (12 * eps)
    rel = np.abs(g - fd) / np.abs(fd)
    print(f"reverse {g}, FD {fd}, rel. error {rel}")
    assert np.all(rel <= 1e-6), (g, fd, rel)


def test_choice_of_the_block_solve(monkeypatch):
    """"auto" takes the multigrid for 3D meshes from AUTO_AMG_UNKNOWNS position unknowns
    on; "lu"/"amg" force a path; Direct() always factors; a bad name is refused."""
    from jaxvisco._solver import _linear

    small3d, small2d = _scene(3, 1), _scene(2, 1)
    assert jv.GMRES().preconditioner == "auto"
    assert jv.GMRES().block_solver(small3d) == "lu"
    monkeypatch.setattr(_linear, "AUTO_AMG_UNKNOWNS", small3d.disc.n_nodes * 3)
    assert jv.GMRES().block_solver(small3d) == "amg"
    assert jv.GMRES().block_solver(small2d) == "lu"  # 2D: the LU's fill stays small
    assert jv.GMRES(preconditioner="lu").block_solver(small3d) == "lu"
    assert jv.GMRES(preconditioner="amg").block_solver(small2d) == "amg"
    assert jv.Direct().block_solver(small3d) == "lu"
    with pytest.raises(ValueError, match=r"GMRES: preconditioner must be one of \('auto', 'lu', 'amg'\), got 'ilu'"):
        jv.GMRES(preconditioner="ilu")
    with pytest.raises(ValueError, match=r"multigrid_precision must be one of \('single', 'double'\), got 'half'"):
        jv.GMRES(multigrid_precision="half")


@pytest.mark.timeout(600)
def test_single_precision_cycles(monkeypatch):
    """The multigrid's operators are stored in float32 by default (`GMRES.multigrid_
    precision`), float64 with "double"; the float32 cycle contracts like the float64 one,
    and its block solve to `CHORD_RTOL` reaches that tolerance on the float64 block,
    returning float64 and the float64 solve's result to float32 rounding."""
    monkeypatch.setattr(_amg, "MAX_COARSE", 60)
    scene, scheme = _scene(3, 2), jv.eG(1)
    hier, mg32 = _multigrid(scene, scheme, dtype=jv.GMRES().block_dtype())
    _, mg64 = _multigrid(scene, scheme, dtype=jv.GMRES(multigrid_precision="double").block_dtype())
    floats = lambda mg: {a.dtype for a in jax.tree_util.tree_leaves(mg) if jnp.issubdtype(a.dtype, jnp.floating)}  # noqa: E731
    assert floats(mg32) == {jnp.dtype(jnp.float32)} and floats(mg64) == {jnp.dtype(jnp.float64)}
    r32 = _cycle_rate(scene, scheme, built=(hier, mg32))[0]
    r64 = _cycle_rate(scene, scheme, built=(hier, mg64))[0]
    assert 0.1 < r64 < 0.6 and abs(r32 - r64) < 0.01 * r64, (r32, r64)
    b = jax.random.normal(jax.random.PRNGKey(2), (scene.disc.n_nodes, scene.dim))
    rel = lambda x: float(jnp.linalg.norm(b - _amg.matvec(hier, mg64, x)) / jnp.linalg.norm(b))  # noqa: E731
    solve = jax.jit(lambda mg: _amg.solve(hier, mg, b, rtol=_amg.CHORD_RTOL))
    x32, x64 = solve(mg32), solve(mg64)
    assert x32.dtype == jnp.float64
    assert rel(x32) <= _amg.CHORD_RTOL and rel(x64) <= _amg.CHORD_RTOL
    # same cycles: one more or fewer would change x by ~the rate (0.4), not 1e-4
    np.testing.assert_allclose(np.asarray(x32), np.asarray(x64), rtol=0, atol=1e-4 * np.abs(np.asarray(x64)).max())


@pytest.mark.timeout(900)
def test_restarted_gmres_on_the_multigrid_path(monkeypatch):
    """GMRES restarted after every 2 vectors (the multigrid path's memory bound, pushed
    to the limit) ends where the direct path does, to the Newton tolerance, and keeps
    eG's energy balance; the restarts cost Krylov vectors, not accuracy."""
    monkeypatch.setattr(_amg, "MAX_COARSE", 40)
    scene = _scene(2, 2, None, held=True)
    steps, h = 4, 0.1
    ends = {}
    for name, lin in [("lu", jv.GMRES(preconditioner="lu", refresh_after=30)),
                      ("amg", jv.GMRES(preconditioner="amg", refresh_after=30)),
                      ("amg2", jv.GMRES(preconditioner="amg", refresh_after=30, restart=2))]:
        sol = jv.simulate(scene, jv.eG(1), t1=steps * h, dt0=h, root_finder=jv.NewtonKrylov(linear_solver=lin, chord=0),
                          saveat=jv.SaveAt(every=steps))
        assert sol.status == "done", sol.status
        ends[name] = sol
    kits = {n: int(np.sum(s.krylov_iterations)) for n, s in ends.items()}
    assert kits["amg2"] > kits["amg"], kits
    scale = np.abs(np.asarray(ends["lu"].x[-1])).max()
    np.testing.assert_allclose(np.asarray(ends["amg2"].x[-1]), np.asarray(ends["lu"].x[-1]), rtol=0, atol=1e-8 * scale)
    H, D, W = (np.asarray(a) for a in (ends["amg2"].energy, ends["amg2"].dissipated, ends["amg2"].external_work))
    assert abs((H[-1] + D[-1] - W[-1]) - H[0]) < 1e-8 * abs(H[0])


def _int_constant_elements(text):
    """Elements of the integer array constants in a lowered program's text."""
    total = 0
    for dims in re.findall(r"stablehlo\.constant dense<[^\n]*?> : tensor<((?:\d+x)+)i(?:32|64)>", text):
        total += int(np.prod([int(d) for d in dims.rstrip("x").split("x")]))
    return total


@pytest.mark.timeout(600)
def test_time_loop_takes_the_hierarchy_as_arguments(monkeypatch):
    """`simulate` passes the hierarchy's index arrays into its compiled loop as arguments
    (`_tangent.multigrid_arguments`): the lowered loop embeds none of them as constants
    (where reading them as constants embeds several times their size), and runs to the
    same steps as the loop that reads them as constants."""
    monkeypatch.setattr(_amg, "MAX_COARSE", 40)
    scene = _scene(3, 1, "hex8", held=True)
    solver = jv.NewtonKrylov(linear_solver=jv.GMRES(preconditioner="amg"))
    run, captured = capture_time_loop(monkeypatch)
    sol = jv.simulate(scene, jv.eG(1), t1=0.3, dt0=0.1, root_finder=solver)
    args, kwargs = captured["args"], captured["kwargs"]
    multigrid = args[-1]
    hier = _amg.of_scene(1, scene)
    assert set(multigrid) == set(hier.arguments())
    size = sum(int(np.size(a)) for a in multigrid.values())
    with_arguments = _int_constant_elements(run.lower(*args, **kwargs).as_text())
    as_constants = _int_constant_elements(run.lower(*args[:-1], None, **kwargs).as_text())
    assert as_constants > 0.5 * size, (as_constants, size)  # (not every index array is read by the loop)
    assert with_arguments < 0.1 * size, (with_arguments, size)
    ref = run(*args[:-1], None, **kwargs)
    n = len(np.asarray(sol.newton_iterations))
    for name in ("newton_iterations", "chord_iterations", "krylov_iterations"):
        np.testing.assert_array_equal(np.asarray(getattr(ref, name))[:n], np.asarray(getattr(sol, name)))
    x, x_ref = np.asarray(sol.x), np.asarray(ref.x)[: len(sol.x)]
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-12 * np.abs(x_ref).max())


@pytest.mark.timeout(600)
def test_multigrid_step_forms_a_stale_tangent_at_its_start(monkeypatch):
    """On the multigrid path a step with a stale tangent forms one at its predictor (the
    one place it forms one) and converges; Newton–Krylov keeps it, and a refresh it asks
    for (`refresh_after=0`: after any Krylov vector) marks the returned tangent stale for
    the next step, where without one the tangent is kept fitting."""
    from jaxvisco._solver._newton import solve_step

    monkeypatch.setattr(_amg, "MAX_COARSE", 40)
    scene, scheme = _scene(2, 2), jv.eG(1)
    ctx = make_context(scene, scene.initial_state(), 0.0, 0.1)
    U0 = predictor(scheme, scene, ctx, scene.v0)

    def step(refresh_after, chord):
        solver = jv.NewtonKrylov(linear_solver=jv.GMRES(preconditioner="amg", refresh_after=refresh_after), chord=chord)
        tan0 = _tangent.empty_tangent(scheme, scene, solver)
        out = jax.jit(lambda c, u, t: solve_step(solver, scheme, scene, c, u, t))(ctx, U0, tan0)
        assert bool(out.converged)
        return out

    kept = step(30, 0)  # Newton–Krylov from a fresh tangent, no refresh asked
    assert int(kept.iterations) > 0 and int(kept.krylov_iterations) > 0
    assert not bool(kept.tangent.stale) and float(kept.tangent.h) == 0.1
    asked = step(0, 0)
    assert int(asked.krylov_iterations) > 0 and bool(asked.tangent.stale)
    chord = step(30, 10)  # the default start: chord iterations on the tangent formed at the predictor
    assert int(chord.chord_iterations) > 0 and int(chord.iterations) == 0 and not bool(chord.tangent.stale)
