"""The step Jacobian and the condensed tangent, checked as identities.

At an arbitrary (unconverged) point U of a time element:
- the residual's JVP (what GMRES multiplies with) matches central differences;
- the block solve with the tangent formed at U inverts the JVP: it is the exact inverse
  of the step Jacobian where the tangent was formed. This holds with the points' local
  Jacobians formed in one pass and in several (`_tangent._POINTS_PER_PASS`).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference, rel_err

import jaxvisco as jv
from jaxvisco._solver import _tangent
from jaxvisco._solver._tangent import form_tangent, schur_solve
from jaxvisco._time_element._step import Unknowns, make_context, predictor, residual


def _scene(viscous, fixed):
    mesh = jv.lshape_mesh(dim=2, refinement=1)
    nh = jv.NeoHooke(lam=3000.0, mu=750.0)
    material = jv.ReeseGovindjee(nh, nh if viscous else None, eta_dev=50.0, eta_vol=10.0)
    X = np.asarray(mesh.points)
    v0 = 0.3 * np.stack([-X[:, 1], X[:, 0]], axis=-1) + np.array([0.5, -0.2])
    kw = dict(fixed=np.broadcast_to((X[:, 1] < 1e-9)[:, None], X.shape)) if fixed else {}
    return jv.Scene(mesh, material, 1.0, velocities=v0, **kw)


def _point(scheme, scene, seed=0):
    """A step context after a strained start and a perturbed predictor (nothing at rest)."""
    rng = np.random.default_rng(seed)
    state = scene.initial_state()
    x = state.x + 0.02 * jnp.asarray(rng.standard_normal(state.x.shape))
    gamma = None
    if state.gamma is not None:
        gamma = state.gamma + 0.01 * jnp.asarray(rng.standard_normal(state.gamma.shape))
        gamma = 0.5 * (gamma + jnp.swapaxes(gamma, -1, -2))
    state = jv.State(x, state.p, gamma)
    ctx = make_context(scene, state, 0.0, 0.1)
    U = predictor(scheme, scene, ctx, scene.v0)
    U = jax.tree_util.tree_map(lambda u: u + 0.01 * jnp.asarray(rng.standard_normal(u.shape)), U)
    v = jax.tree_util.tree_map(lambda u: jnp.asarray(rng.standard_normal(u.shape)), U)
    if scene.fixed is not None:
        # Newton's corrections never move a held component (the predictor puts it in
        # place and its residual row stays zero); the block solve drops the coupling of
        # free rows to held columns, so it is exact on that subspace only.
        v = Unknowns(jnp.where(jnp.asarray(scene.fixed.array)[None], 0.0, v.x), v.g)
    return ctx, U, v


def _flat(u):
    return jnp.concatenate([jnp.ravel(a) for a in jax.tree_util.tree_leaves(u)])


SCHEMES = [jv.eG(1), jv.eG(2), jv.cG(2), jv.Newmark()]


@pytest.mark.timeout(600)
@pytest.mark.parametrize("scheme", SCHEMES, ids=lambda s: s.name)
@pytest.mark.parametrize("viscous,fixed", [(True, False), (False, False), (True, True)],
                         ids=["viscous", "elastic", "held-nodes"])
def test_jacobian_and_block_solve_are_exact(scheme, viscous, fixed, monkeypatch):
    scene = _scene(viscous, fixed)
    ctx, U, v = _point(scheme, scene)
    if viscous and not fixed:
        # 156 points: passes of 50 points, the last one padded.
        monkeypatch.setattr(_tangent, "_POINTS_PER_PASS", 50)

    @jax.jit
    def evaluate(ctx, U, v):
        _, jvp = jax.linearize(lambda u: residual(scheme, scene, ctx, u), U)
        Jv = jvp(v)
        tan = form_tangent(scheme, scene, ctx, U)
        return Jv, schur_solve(scheme, scene, ctx, tan, Jv)

    Jv, w = evaluate(ctx, U, v)
    res = jax.jit(lambda u: _flat(residual(scheme, scene, ctx, u)))
    fd = central_difference(res, U, v, eps=1e-5, order=4)
    assert rel_err(_flat(Jv), fd) < 1e-7, rel_err(_flat(Jv), fd)
    # The block solve is the inverse of the Jacobian at the point the tangent was formed.
    err = rel_err(_flat(w), _flat(v))
    assert err < 1e-9, err
    if viscous:
        assert isinstance(w, Unknowns) and w.g is not None


@pytest.mark.timeout(300)
@pytest.mark.parametrize("scheme", [jv.eG(1), jv.eG(2), jv.cG(2)], ids=lambda s: s.name)
@pytest.mark.parametrize("d,viscous", [(3, True), (2, True), (3, False)], ids=["3D", "2D", "3D-elastic"])
def test_point_tangent_by_directions_equals_jacfwd(scheme, d, viscous):
    """The multigrid path's point sensitivities (`jacobian_by_directions`: one JVP per
    direction in a scan) equal `jax.jacfwd`'s at strained points, to rounding."""
    rng = np.random.default_rng(7)
    nh = jv.NeoHooke(lam=3000.0, mu=750.0)
    material = jv.ReeseGovindjee(nh, nh if viscous else None, eta_dev=50.0, eta_vol=10.0)
    n, k = 6, scheme.k
    F = jnp.asarray(np.eye(3) + 0.1 * rng.standard_normal((n, k + 1, 3, 3)))
    if d == 2:
        F = F.at[..., 2, :2].set(0.0).at[..., :2, 2].set(0.0)
    G = None
    if viscous:
        a = 0.05 * rng.standard_normal((n, k + 1, 3, 3))
        G = jnp.asarray(np.eye(3) + a + np.swapaxes(a, -1, -2))
    point = lambda directions: jax.jit(jax.vmap(lambda f, g: _tangent._point_tangent(  # noqa: E731
        scheme, material, 0.1, f, g, d=d, directions=directions)))
    by_directions, forward = point(True)(F, G), point(False)(F, G)
    for a, b in zip(by_directions, forward):
        if b is None:
            assert a is None
            continue
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(b))))


@pytest.mark.parametrize("unroll", [1, 5])
def test_jacobian_by_directions_of_three_inputs(unroll, monkeypatch):
    monkeypatch.setattr(_tangent, "DIRECTIONS_PER_ITERATION", unroll)

    def fun(a, b, c):
        return {"u": jnp.sin(a) @ b, "v": jnp.exp(c) * jnp.sum(a)}

    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    xs = (jax.random.normal(keys[0], (2, 3)), jax.random.normal(keys[1], (3,)), jax.random.normal(keys[2], (2,)))
    got = _tangent.jacobian_by_directions(fun, *xs)  # 11 directions: unrolled by 5, a remainder
    want = jax.jacfwd(fun, argnums=(0, 1, 2))(*xs)
    jax.tree_util.tree_map(functools.partial(np.testing.assert_allclose, rtol=1e-14, atol=1e-14), got, want)


@pytest.mark.timeout(120)
def test_map_in_passes_values_and_derivatives():
    """`map_in_passes` on rows that do not fill the last pass (23 rows in passes of 5):
    values, forward and reverse derivatives equal the one-pass map's."""
    from jaxvisco._fem._passes import map_in_passes

    def fn(xs):
        a, b = xs
        return {"s": jnp.sin(a) * b[:, :1], "t": jnp.einsum("nij,nj->ni", jnp.exp(0.1 * b[:, :, None] * a[:, None, :]), b)}

    keys = jax.random.split(jax.random.PRNGKey(3), 4)
    xs = (jax.random.normal(keys[0], (23, 4)), jax.random.normal(keys[1], (23, 4)))
    dx = (jax.random.normal(keys[2], (23, 4)), jax.random.normal(keys[3], (23, 4)))
    passes = jax.jit(lambda x: map_in_passes(fn, x, 5))
    close = functools.partial(np.testing.assert_allclose, rtol=1e-13, atol=1e-13)
    jax.tree_util.tree_map(close, passes(xs), fn(xs))
    jax.tree_util.tree_map(close, jax.jvp(passes, (xs,), (dx,))[1], jax.jvp(fn, (xs,), (dx,))[1])
    weight = lambda f: lambda x: sum(jnp.sum(jnp.cos(o)) for o in jax.tree_util.tree_leaves(f(x)))  # noqa: E731
    jax.tree_util.tree_map(close, jax.grad(weight(passes))(xs), jax.grad(weight(fn))(xs))


@pytest.mark.timeout(300)
@pytest.mark.parametrize("parts", [False, True], ids=["one-material", "two-parts"])
def test_residual_in_passes_equals_one_pass(parts, monkeypatch):
    """Large meshes evaluate the step residual's points in passes (`_fem._passes`): the
    residual and its JVP equal the one-pass forms, with one material and with a material
    per cell."""
    import jaxvisco._scene as scene_module

    if parts:
        from test_loads import _two_part_scene, _viscous
        scene, _ = _two_part_scene(_viscous(60.0, 15.0, 5.0, 25.0), _viscous(30.0, 7.5, 10.0, 50.0), rho_left=20.0)
        assert scene.cell_material is not None
    else:
        scene = _scene(True, False)
    scheme = jv.eG(2)
    ctx, U, v = _point(scheme, scene)

    def evaluate(ctx, U, v):
        return jax.jvp(lambda u: residual(scheme, scene, ctx, u), (U,), (v,))

    one = jax.jit(evaluate)(ctx, U, v)
    cells = 3 if parts else 5  # per pass: several passes, the last one padded (4 and 39 cells)
    assert scene.disc.n_cells > cells and scene.disc.n_cells % cells
    monkeypatch.setattr(scene_module, "POINTS_PER_PASS", cells * scene.disc.n_qp)
    passes = jax.jit(evaluate)(ctx, U, v)
    for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(passes)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=1e-13 * np.abs(np.asarray(a)).max())
