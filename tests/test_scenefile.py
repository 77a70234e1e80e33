"""Scene files: the same run as the Python scene, groups from Gmsh and Abaqus files,
`jaxvisco run SCENE.toml` with --resume, the template, and every kind of bad input.

Compilation is the cost: every run here is the 2D strip of 4 x 2 quad4 cells with the
same clamp and load structure, or the paper's L-shape, in chunks of 3 steps, so that the
whole file compiles a handful of programs."""

import os

import meshio
import numpy as np
import pytest

import jaxvisco as jv
from jaxvisco import (
    boundary_facets,
    facets_from_nodes,
    local_facets,
    pressure_load,
    read_scene_file,
    traction_load,
)
from jaxvisco._scenefile._scenefile import tomllib
from jaxvisco.cli import main
from jaxvisco.cli._main import run_chunked
from jaxvisco.time_functions import Ramp, Step

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = os.path.join(HERE, os.pardir, "examples", "scenes")

MATERIAL = """
[material]
lam = 30000.0
mu = 7500.0
eta_dev = 5000.0
eta_vol = 10000.0
density = 8.93
"""
# The strip [0, 2] x [0, 1], 4 x 2 quad4 cells, clamped at x = 0, a nodal load on the
# tip nodes switched off at t = 0.2 and a ramped traction on the top edge.
GROUPS = """
[groups.clamp]
x = 0.0

[groups.tip]
x = [2.0, 2.0]

[groups.top]
y = 1.0
"""
BODY = MATERIAL + """
[initial]
velocity = [0.0, 1.0]

[[dirichlet]]
nodes = "clamp"
components = "all"

[[load]]
nodes = "tip"
force = [0.0, -50.0]
time = { type = "step", at = 0.2, before = 1.0, after = 0.0 }

[[traction]]
facets = "top"
traction = [5.0, -20.0]
time = { type = "ramp", t0 = 0.0, t1 = 0.3 }

[integrator]
name = "eG"
order = 1

[time]
t_end = 0.3
dt = 0.1

[output]
file = "strip.h5"
chunk = 3
commit_every = 0
"""
STRIP = """
[mesh]
generator = "rectangle"
nx = 4
ny = 2
lx = 2.0
ly = 1.0
""" + GROUPS + BODY


def python_strip():
    """The strip scene built with the Python API."""
    mesh = jv.rectangle(4, 2, 2.0, 1.0)
    X = np.asarray(mesh.points)
    clamp, tip = np.isclose(X[:, 0], 0.0), np.isclose(X[:, 0], 2.0)
    top = facets_from_nodes(mesh, np.flatnonzero(np.isclose(X[:, 1], 1.0)))
    nh = jv.NeoHooke(lam=30000.0, mu=7500.0)
    material = jv.ReeseGovindjee(nh, nh, eta_dev=5000.0, eta_vol=10000.0)
    fixed = np.zeros(X.shape, dtype=bool)
    fixed[clamp] = True
    f_tip = np.zeros(X.shape)
    f_tip[tip] = [0.0, -50.0]
    loads = [(f_tip, Step(at=0.2, before=1.0, after=0.0)),
             (traction_load(mesh, top, np.array([5.0, -20.0])), Ramp(t0=0.0, t1=0.3))]
    v0 = np.broadcast_to([0.0, 1.0], X.shape)
    return jv.Scene(mesh, material, 8.93, velocities=v0, fixed=fixed, loads=loads)


def run_python(scene, t_end, path):
    """The CLI's driver on a Python scene, chunks of 3 steps, into a results file."""
    w = jv.ResultsWriter(path, scene)
    try:
        r = run_chunked(scene, jv.eG(1), jv.StepTo.from_schedule(0.0, t_end, 0.1), chunk=3, commit_every=0.0,
                        writer=w, quiet=True)
    finally:
        w.close(status="done")
    assert r["status"] == "done"
    return jv.read_results(path)


def assert_same_run(a, b, tol=1e-12):
    np.testing.assert_array_equal(a["t"], b["t"])
    assert np.max(np.abs(a["x"] - b["x"])) <= tol * np.max(np.abs(b["x"]))
    assert np.max(np.abs(a["energy"] - b["energy"])) <= tol * np.max(np.abs(b["energy"]))


@pytest.fixture(scope="module")
def strip_run(tmp_path_factory):
    """`jaxvisco run strip.toml` (3 steps, output named by the file), then the Python run."""
    d = tmp_path_factory.mktemp("strip")
    (d / "strip.toml").write_text(STRIP)
    assert main(["run", str(d / "strip.toml"), "--quiet"]) == 0
    return d, jv.read_results(d / "strip.h5"), run_python(python_strip(), 0.3, d / "python.h5")


# ---------------------------------------------------------------- the same run


def test_scene_file_equals_python_scene(strip_run):
    _, cli, py = strip_run
    assert len(cli["t"]) == 4 and cli["attrs"]["status"] == "done"
    assert_same_run(cli, py)
    assert np.max(np.abs(cli["x"][-1] - cli["x"][0])) > 1e-3  # it moved
    X = cli["points"]
    np.testing.assert_array_equal(cli["x"][:, X[:, 0] == 0.0], np.broadcast_to(X[X[:, 0] == 0.0], (4, 3, 2)))
    # eG(1) with loads: H + dissipated - work of the loads stays H(0)
    balance = cli["energy"] + cli["dissipated"] - cli["external_work"] - cli["energy"][0]
    assert np.max(np.abs(balance)) < 1e-8 * np.max(np.abs(cli["external_work"]))
    assert np.max(np.abs(cli["external_work"])) > 0


def test_scene_arrays_equal_python_scene(tmp_path):
    (tmp_path / "s.toml").write_text(STRIP)
    a, b = jv.Scene.from_file(tmp_path / "s.toml"), python_strip()
    np.testing.assert_array_equal(a.fixed.array, b.fixed.array)
    np.testing.assert_array_equal(np.asarray(a.v0), np.asarray(b.v0))
    for t in (0.0, 0.1, 0.2, 0.25, 1.0):
        np.testing.assert_allclose(np.asarray(a.external_force(t)), np.asarray(b.external_force(t)), rtol=0,
                                   atol=1e-13)


def test_resume_continues_from_the_stored_scene(strip_run, tmp_path):
    d, _, _ = strip_run
    (d / "strip.toml").write_text("this is no longer a scene file")  # --resume must not read it
    assert main(["run", "--resume", str(d / "strip.h5"), "--t-end", "0.6", "--quiet"]) == 0
    resumed = jv.read_results(d / "strip.h5")
    assert len(resumed["t"]) == 7 and resumed["attrs"]["status"] == "done"
    assert_same_run(resumed, run_python(python_strip(), 0.6, tmp_path / "whole.h5"))


# ---------------------------------------------------------------- groups from mesh files


def write_strip_gmsh(path):
    """The strip with Gmsh physical groups: lines "clamp", "top", points "tip"."""
    mesh = jv.rectangle(4, 2, 2.0, 1.0)
    X, edges = np.asarray(mesh.points), boundary_facets(mesh)
    left, top = edges[np.all(X[edges, 0] == 0.0, 1)], edges[np.all(X[edges, 1] == 1.0, 1)]
    tip = np.flatnonzero(X[:, 0] == 2.0)[:, None]
    cells = [("quad", np.asarray(mesh.cells)), ("line", left), ("line", top), ("vertex", tip)]
    tags = [np.full(len(c), i + 1) for i, (_, c) in enumerate(cells)]
    field = {"body": np.array([1, 2]), "clamp": np.array([2, 1]), "top": np.array([3, 1]), "tip": np.array([4, 0])}
    meshio.write(path, meshio.Mesh(np.column_stack([X, np.zeros(len(X))]), cells, field_data=field,
                                   cell_data={"gmsh:physical": tags, "gmsh:geometrical": tags}),
                 file_format="gmsh22", binary=False)


def write_strip_abaqus(path):
    """The strip as Abaqus CPS4 cells with *NSET clamp, tip, *ELSET, *SURFACE top."""
    mesh = jv.rectangle(4, 2, 2.0, 1.0)
    X, cells = np.asarray(mesh.points), np.asarray(mesh.cells)
    lines = ["*NODE"] + [f"{i + 1}, {float(x)!r}, {float(y)!r}" for i, (x, y) in enumerate(X)]
    lines += ["*ELEMENT, TYPE=CPS4, ELSET=ALL"] + [f"{e + 1}, " + ", ".join(str(a + 1) for a in c)
                                                  for e, c in enumerate(cells)]
    for name, mask in (("CLAMP", X[:, 0] == 0.0), ("TIP", X[:, 0] == 2.0)):
        lines += [f"*NSET, NSET={name}", ", ".join(str(i + 1) for i in np.flatnonzero(mask))]
    on_top = np.all(X[cells[:, local_facets("quad4")], 1] == 1.0, axis=2)
    e, k = np.nonzero(on_top)
    lines += ["*ELSET, ELSET=UPPER", ", ".join(str(i + 1) for i in e)]
    lines += ["*SURFACE, NAME=TOP, TYPE=ELEMENT", f"UPPER, S{k[0] + 1}"]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("kind", ["gmsh", "abaqus"])
def test_mesh_file_groups_drive_clamps_and_loads(kind, strip_run, tmp_path):
    mesh_file = tmp_path / ("strip.msh" if kind == "gmsh" else "strip.inp")
    (write_strip_gmsh if kind == "gmsh" else write_strip_abaqus)(mesh_file)
    text = f'[mesh]\nfile = "{mesh_file.name}"\n' + BODY
    if kind == "abaqus":  # Abaqus names are looked up ignoring case
        text = text.replace('"clamp"', '"Clamp"').replace('"top"', '"TOP"')
    (tmp_path / "s.toml").write_text(text)
    scene = jv.Scene.from_file(tmp_path / "s.toml")
    ref = python_strip()
    np.testing.assert_array_equal(scene.mesh.points, ref.mesh.points)
    np.testing.assert_array_equal(scene.fixed.array, ref.fixed.array)
    for t in (0.1, 0.25):
        np.testing.assert_allclose(np.asarray(scene.external_force(t)), np.asarray(ref.external_force(t)), rtol=0,
                                   atol=1e-13)
    # the run they drive is the scene file's run with coordinate groups
    _, cli, _ = strip_run
    assert_same_run(run_python(scene, 0.3, tmp_path / "r.h5"), cli)


def test_example_scenes_read():
    beam = read_scene_file(os.path.join(SCENES, "beam2d.toml"))
    X = np.asarray(beam.scene.mesh.points)
    np.testing.assert_array_equal(beam.scene.fixed.array.any(1), X[:, 0] == 0.0)  # Gmsh line "left"
    np.testing.assert_allclose(np.asarray(beam.scene.external_force(0.5)).sum(0), [0.0, -20.0], atol=1e-12)
    assert not np.asarray(beam.scene.external_force(1.0)).any()  # switched off at t = 1
    block = read_scene_file(os.path.join(SCENES, "block3d_pressure.toml"))
    X = np.asarray(block.scene.mesh.points)
    np.testing.assert_array_equal(block.scene.fixed.array.any(1), X[:, 0] == 0.0)  # *NSET CLAMP
    end = facets_from_nodes(block.scene.mesh, np.flatnonzero(np.isclose(X[:, 0], 2.0)))
    np.testing.assert_allclose(np.asarray(block.scene.external_force(1.0)),  # *SURFACE LOADED, ramp done
                               np.asarray(pressure_load(block.scene.mesh, end, 1000.0)), atol=1e-12)
    np.testing.assert_allclose(np.asarray(block.scene.external_force(0.25)).sum(0), [-500.0, 0, 0], atol=1e-9)


def test_paper_scene_is_the_builtin_scene():
    """paper.toml describes the built-in L-shape exactly (same pytree, same arrays, bit
    for bit), so its runs are those of `jaxvisco run` (the run itself: the slow test)."""
    import jax

    from jaxvisco.cli._main import make_scene

    sf = read_scene_file(os.path.join(SCENES, "paper.toml"))
    a, ta = jax.tree_util.tree_flatten(sf.scene)
    b, tb = jax.tree_util.tree_flatten(make_scene())
    assert ta == tb and len(a) == len(b)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert sf.integrator.name == "eG(1)" and sf.dt == ((20.0, 0.1), (24.0, 1.0)) and len(sf.steps) == 204


@pytest.mark.slow
def test_paper_scene_equals_builtin_run(tmp_path):
    common = ["--t-end", "0.3", "--dt", "0.1", "--chunk", "3", "--commit-every", "0", "--quiet"]
    assert main(["run", "--integrator", "eG", "--out", str(tmp_path / "builtin.h5")] + common) == 0
    assert main(["run", os.path.join(SCENES, "paper.toml"), "--out", str(tmp_path / "file.h5")] + common) == 0
    a, b = jv.read_results(tmp_path / "file.h5"), jv.read_results(tmp_path / "builtin.h5")
    assert len(a["t"]) == 4
    np.testing.assert_array_equal(a["x"], b["x"])
    np.testing.assert_array_equal(a["energy"], b["energy"])
    assert a["attrs"]["scene"].startswith("scenefile:") and b["attrs"]["scene"] == "lshape"


KEYS_TEXT = """
[mesh]
generator = "box"
nx = 2
ny = 1
nz = 1
lx = 2.0
quadrature_order = 2
[groups.left]
x = 0.0
[groups.right]
x = [1.999, 2.5]
[groups.corner]
x = 1.0
y = [0.5, 1.0]
z = 1.0
[material]
density = 2.0
mass = "lumped"
eta_dev = 10.0
[material.equilibrium]
lam = 1000.0
mu = 500.0
[material.nonequilibrium]
lam = 2000.0
mu = 100.0
[initial]
velocity = [1.0, 0.0, 0.0]
angular_velocity = [0.0, 0.0, 2.0]
center = [1.0, 0.5, 0.5]
[[initial.velocity_field]]
nodes = "corner"
value = [0.0, 0.0, 7.0]
[[dirichlet]]
nodes = ["left", "corner"]
components = [0]
[[dirichlet]]
nodes = "right"
components = ["x", "z"]
displacement = [0.1, 0.0, -0.2]
time = { type = "table", times = [0.0, 1.0], values = [0.0, 1.0] }
[solver]
rtol = 1e-12
linear_solver = "direct"
chord = 0
[integrator]
name = "cg"
order = 2
[time]
schedule = [[0.5, 0.1], [1.5, 0.25]]
"""


def test_scene_file_keys(tmp_path):
    """Material branches, mass, quadrature, initial velocities, prescribed motion, group
    lists, integer components, the solver table and a 3D generator, read into the scene."""
    text = KEYS_TEXT
    (tmp_path / "k.toml").write_text(text)
    sf = read_scene_file(tmp_path / "k.toml")
    s, X = sf.scene, np.asarray(sf.scene.mesh.points)
    m = s.material
    assert (float(m.equilibrium.lam), float(m.equilibrium.mu)) == (1000.0, 500.0)
    assert (float(m.nonequilibrium.lam), float(m.nonequilibrium.mu)) == (2000.0, 100.0)
    assert float(m.eta_dev) == 10.0 and np.isinf(float(m.eta_vol)) and float(s.density) == 2.0
    mass_el = np.asarray(s.disc.mass_el)
    assert np.all(mass_el == mass_el * np.eye(8)) and s.disc.n_qp == 8  # lumped; 2 x 2 x 2 points
    left, right = X[:, 0] == 0.0, X[:, 0] == 2.0
    corner = (X[:, 0] == 1.0) & (X[:, 1] == 1.0) & (X[:, 2] == 1.0)
    assert corner.sum() == 1
    fixed = s.fixed.array
    np.testing.assert_array_equal(fixed[:, 0], left | right | corner)
    np.testing.assert_array_equal(fixed[:, 1], np.zeros(len(X), bool))
    np.testing.assert_array_equal(fixed[:, 2], right)
    v = np.asarray(s.v0)
    free = ~(left | right | corner)
    expect = [1.0, 0.0, 0.0] + np.cross([0.0, 0.0, 2.0], X - [1.0, 0.5, 0.5])
    np.testing.assert_allclose(v[free], expect[free], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(v[corner], [[0.0, 0.0, 7.0]])  # the field, x held: 0
    u = np.asarray(s.held_positions(0.5)) - X
    np.testing.assert_allclose(u[right], np.broadcast_to([0.05, 0.0, -0.1], (right.sum(), 3)), atol=1e-15)
    assert not u[~right].any()
    assert sf.solver.rtol == 1e-12 and sf.solver.linear_solver == jv.Direct() and sf.solver.chord == 0
    assert sf.integrator.name == "cG(2)" and sf.t_end == 1.5 and len(sf.steps) == 9
    # the elastic form: no viscosity, one branch and no internal variable; "inf" as text
    elastic = text.replace("eta_dev = 10.0", 'eta_vol = "inf"').replace("[material.nonequilibrium]\nlam = 2000.0\n"
                                                                       "mu = 100.0\n", "")
    (tmp_path / "e.toml").write_text(elastic)
    assert not read_scene_file(tmp_path / "e.toml").scene.has_internal_variable


def test_solver_keys_set_the_gmres(tmp_path):
    """[solver]'s krylov, krylov_max_steps and refresh_after (file keys of 0.1),
    preconditioner, restart and multigrid_precision fill NewtonKrylov's GMRES."""
    text = KEYS_TEXT.replace('linear_solver = "direct"', 'linear_solver = "krylov"\nkrylov = "lineax"\n'
                             'krylov_max_steps = 30\nrefresh_after = 2\npreconditioner = "amg"\nrestart = 10\n'
                             'multigrid_precision = "double"', 1)
    (tmp_path / "g.toml").write_text(text)
    solver = read_scene_file(tmp_path / "g.toml").solver
    assert solver.linear_solver == jv.GMRES(max_steps=30, refresh_after=2, backend="lineax", preconditioner="amg",
                                            restart=10, multigrid_precision="double")
    assert solver.rtol == 1e-12


@pytest.mark.parametrize("old,new,message", [
    ("displacement = [0.1, 0.0, -0.2]", "displacement = [0.1, 0.3, -0.2]",
     "[[dirichlet]] 2: displacement: component 'y' is 0.3 but not held"),
    ('values = [0.0, 1.0]', 'values = [1.0, 1.0]', "[[dirichlet]] 2: time: g(0) = 1.0; prescribed motion must start"),
    ("displacement = [0.1, 0.0, -0.2]\n", "", "[[dirichlet]] 2: time: a time function needs a `displacement`"),
    ("rtol = 1e-12", "rtoll = 1e-12", "[solver]: unknown key 'rtoll'; accepted: rtol, max_iterations"),
    ("rtol = 1e-12", "rtol = 2.0", "[solver]: rtol must lie in (0, 1), got 2.0."),
    ('linear_solver = "direct"', 'linear_solver = "krylov"\nkrylov = "cg"',
     "[solver]: krylov must be one of ('gmres', 'lineax'), got 'cg'."),
    ("chord = 0", "chord = 0\nrefresh_after = 2",
     "[solver]: krylov, krylov_max_steps, refresh_after, preconditioner, restart and multigrid_precision set the "
     "Krylov solver, but linear_solver = 'direct'."),
    ('linear_solver = "direct"', 'linear_solver = "krylov"\nmultigrid_precision = "half"',
     "[solver]: GMRES: multigrid_precision must be one of ('single', 'double'), got 'half'."),
    ('linear_solver = "direct"', 'linear_solver = "krylov"\nrestart = 0',
     "[solver]: GMRES: restart must be None or an integer >= 1, got 0."),
    ('linear_solver = "direct"', 'linear_solver = "krylov"\npreconditioner = "ilu"',
     "[solver]: GMRES: preconditioner must be one of ('auto', 'lu', 'amg'), got 'ilu'."),
    ('linear_solver = "direct"', 'linear_solver = "lu"',
     "[solver]: linear_solver must be GMRES(...), Direct() or one of ('krylov', 'direct'), got 'lu'."),
    ('name = "cg"\norder = 2', 'name = "Newmark"\norder = 2', "[integrator]: order: Newmark has no order"),
    ("eta_dev = 10.0", "eta_dev = 10.0\nlam = 1.0", "[material]: lam: give lam/mu or [material.equilibrium], not"),
    ("[material.nonequilibrium]\nlam = 2000.0\nmu = 100.0\n", "",
     "[material]: eta_dev: a finite viscosity needs the viscous branch [material.nonequilibrium]."),
    ("angular_velocity = [0.0, 0.0, 2.0]", "angular_velocity = 2.0",
     "[initial]: angular_velocity: got 2.0; accepted: a list of 3 finite numbers."),
    ("value = [0.0, 0.0, 7.0]", "value = [0.0, 0.0, 7.0]\nnode = 1",
     "[[initial.velocity_field]] 1: unknown key 'node'"),
    ('mass = "lumped"', 'mass = "diagonal"', "[material]: mass: got 'diagonal'; accepted: 'consistent', 'lumped'."),
])
def test_bad_keys(old, new, message, tmp_path):
    text = KEYS_TEXT  # valid as it stands: test_scene_file_keys
    assert old in text
    (tmp_path / "k.toml").write_text(text.replace(old, new, 1))
    with pytest.raises(ValueError) as e:
        read_scene_file(tmp_path / "k.toml")
    assert message in str(e.value) and str(e.value).startswith(str(tmp_path / "k.toml")), str(e.value)


PARTS = STRIP.replace("[initial]", """[groups.soft]
x = [0.0, 1.0]

[[material.part]]
cells = "soft"
lam = 20000.0
mu = 3000.0
eta_vol = inf
density = 4.0

[initial]""")


def test_material_parts(tmp_path):
    (tmp_path / "p.toml").write_text(PARTS)
    s = jv.Scene.from_file(tmp_path / "p.toml")
    X, cells = np.asarray(s.mesh.points), np.asarray(s.mesh.cells)
    soft = X[cells, 0].max(axis=1) <= 1.0  # the cells whose nodes all lie in [groups.soft]
    assert soft.sum() == 4
    which = s.cell_material.array
    m = s.material
    np.testing.assert_array_equal(np.asarray(m.equilibrium.mu)[which], np.where(soft, 3000.0, 7500.0))
    np.testing.assert_array_equal(np.asarray(m.equilibrium.lam)[which], np.where(soft, 20000.0, 30000.0))
    np.testing.assert_array_equal(np.asarray(m.eta_dev)[which], 5000.0)  # from [material]
    np.testing.assert_array_equal(np.asarray(m.eta_vol)[which], np.where(soft, np.inf, 10000.0))
    np.testing.assert_array_equal(np.asarray(s.density), np.where(soft, 4.0, 8.93))  # the part's own density
    # parts alone, covering every cell: a Gmsh cell group
    write_strip_gmsh(tmp_path / "strip.msh")
    text = '[mesh]\nfile = "strip.msh"\n' + BODY.replace("lam = 30000.0\nmu = 7500.0\n", "").replace(
        "[initial]", '[[material.part]]\ncells = "body"\nlam = 1.0\nmu = 2.0\n[initial]')
    (tmp_path / "g.toml").write_text(text)
    s = jv.Scene.from_file(tmp_path / "g.toml")
    assert s.cell_material is None and float(s.material.equilibrium.mu) == 2.0


@pytest.mark.parametrize("old,new,message", [
    ('cells = "soft"', 'cells = "hard"', "[[material.part]] 1: cells: no cell group 'hard'; the mesh has no named "
     "groups and [groups] defines: clamp, soft, tip, top."),
    ('cells = "soft"', 'cells = "top"', "[[material.part]] 1: cells: [groups.top] contains no whole cell"),
    ("eta_vol = inf\n", 'eta_vol = inf\n[[material.part]]\ncells = "soft"\nlam = 1.0\n',
     "[[material.part]] 2: cells: cell 0 is also in [[material.part]] 1; each cell takes one material."),
    ("eta_vol = inf\n", "eta_vol = inf\neta_dev = inf\n", "[material]: part: [[material.part]] 1 is elastic but "
     "[material] is not; the materials of one body must all be viscous or all elastic."),
    ("mu = 3000.0", "muu = 3000.0", "[[material.part]] 1: unknown key 'muu'; accepted: lam, mu, eta_dev, eta_vol, "
     "equilibrium, nonequilibrium, cells, density."),
    ("density = 4.0", "density = -1.0", "[[material.part]] 1: density: "),
    ("lam = 30000.0\nmu = 7500.0\n", "", "[material]: part: 4 of 8 cells (the first: cell 4) are in no "
     "[[material.part]]; give [material] lam/mu"),
])
def test_bad_material_parts(old, new, message, tmp_path):
    assert old in PARTS
    (tmp_path / "p.toml").write_text(PARTS.replace(old, new, 1))
    with pytest.raises(ValueError) as e:
        read_scene_file(tmp_path / "p.toml")
    assert message in str(e.value), str(e.value)


# ---------------------------------------------------------------- the template


def test_template_parses_and_reads(capsys, tmp_path):
    assert main(["scene-template"]) == 0
    text = capsys.readouterr().out
    doc = tomllib.loads(text)
    assert doc["mesh"]["generator"] == "rectangle" and "file" not in doc["mesh"]
    for key in ("file = ", "velocity_field", "angular_velocity", "pressure", "schedule", "[material.equilibrium]",
                "displacement", '"table"', '"sine"', "[solver]", "save_gamma", "commit_every"):
        assert key in text, key  # every key is documented
    (tmp_path / "t.toml").write_text(text)
    sf = read_scene_file(tmp_path / "t.toml")
    X = np.asarray(sf.scene.mesh.points)
    np.testing.assert_array_equal(sf.scene.fixed.array.any(1), X[:, 0] == 0.0)
    # three tip nodes at -2 each and -0.5 per unit length on the top edge of length 4
    np.testing.assert_allclose(np.asarray(sf.scene.external_force(0.5)).sum(0), [0.0, -8.0], atol=1e-12)
    assert len(sf.steps) == 60 and sf.output["file"] == str(tmp_path / "scene.h5")
    assert sf.scene.has_internal_variable


# ---------------------------------------------------------------- bad input

BAD = [
    (("[mesh]", "[mesh2]\nx = 1\n[mesh]"), "s.toml: unknown table [mesh2]; accepted: [mesh], [groups]"),
    (("lam = 30000.0", "lamm = 30000.0"), "s.toml: [material]: unknown key 'lamm'; accepted: lam, mu, eta_dev"),
    (("density = 8.93", ""), "s.toml: [material]: density: missing (required)."),
    (("dt = 0.1", 'dt = "0.1"'), "s.toml: [time]: dt: expected a number, got '0.1'."),
    (("eta_dev = 5000.0", "eta_dev = -1.0"), "s.toml: [material]: eta_dev: got -1.0; accepted: a number > 0 or inf."),
    (('nodes = "tip"', 'nodes = "tipp"'), "s.toml: [[load]] 1: nodes: no node group 'tipp'; the mesh has no named "
     "groups and [groups] defines: clamp, tip, top."),
    (('components = "all"', 'components = ["x", "z"]'),
     "s.toml: [[dirichlet]] 1: components: got 'z' in ['x', 'z']; the mesh is 2D, accepted: \"all\" or a list of "
     "'x', 'y' (or 0..1)."),
    (("force = [0.0, -50.0]", "force = [0.0, -50.0, 1.0]"),
     "s.toml: [[load]] 1: force: got [0.0, -50.0, 1.0]; accepted: a list of 2 finite numbers."),
    (("t0 = 0.0, t1 = 0.3", "t0 = 0.3, t1 = 0.0"), "s.toml: [[traction]] 1: time: Ramp: t1 must be greater than t0"),
    (('type = "step", at', 'type = "step", att'), "s.toml: [[load]] 1: time: unknown key 'att' for type 'step'"),
    (('type = "ramp"', 'type = "linear"'), "s.toml: [[traction]] 1: time: type must be one of"),
    (("traction = [5.0, -20.0]", "traction = [5.0, -20.0]\npressure = 1.0"),
     "s.toml: [[traction]] 1: traction: give either traction"),
    (('facets = "top"', 'facets = "side"'), "s.toml: [[traction]] 1: facets: no facet or node group 'side'; the "
     "mesh has no named groups and [groups] defines: clamp, tip, top."),
    (("[[dirichlet]]", "[dirichlet]"), "s.toml: [dirichlet] must be an array of tables: write [[dirichlet]]"),
    (('name = "eG"', 'name = "RK4"'), "s.toml: [integrator]: name: got 'RK4'; accepted: cG, eG, Newmark, Midpoint."),
    (("dt = 0.1", "schedule = [[0.2, 0.1]]"), "s.toml: [time]: schedule: the dt schedule ends at t = 0.2, before"),
    (("dt = 0.1", "dt = 0.1\nschedule = [[0.3, 0.1]]"), "s.toml: [time]: dt: give either dt"),
    (('generator = "rectangle"', 'generator = "disk"'), "s.toml: [mesh]: generator: got 'disk'; accepted: "),
    (("nx = 4", "nx = 4\nnz = 2"), "s.toml: [mesh]: unknown key 'nz'; accepted: file, generator, nx, ny, lx, ly"),
    (('generator = "rectangle"', 'file = "nowhere.msh"\ngenerator = "rectangle"'), "s.toml: [mesh]: file: give either"),
    (("x = 0.0", "z = 0.0"), "s.toml: [groups.clamp]: z: the mesh is 2D; accepted: x, y."),
    (("x = 0.0", "x = 5.0"), "s.toml: [groups.clamp]: selects no node; the mesh spans x in [0, 2], y in [0, 1]."),
    (("[time]", "[time]\nmax_halvings = 31"), "s.toml: [time]: max_halvings: got 31; accepted: an integer in [0, 30]."),
    (("chunk = 3", "chunk = true"), "s.toml: [output]: chunk: got True; accepted: an integer >= 1."),
    (("lx = 2.0", "lx = 2.0 ="), "s.toml: not valid TOML: "),
]


@pytest.mark.parametrize("edit,message", BAD, ids=[m.split(": ", 2)[-1][:40] for _, m in BAD])
def test_bad_scene_file(edit, message, tmp_path):
    old, new = edit
    assert old in STRIP
    (tmp_path / "s.toml").write_text(STRIP.replace(old, new, 1))
    with pytest.raises(ValueError) as e:
        read_scene_file(tmp_path / "s.toml")
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith(str(tmp_path / "s.toml")) and message in msg, msg


def test_missing_group_lists_the_mesh_groups(tmp_path):
    write_strip_gmsh(tmp_path / "strip.msh")
    text = '[mesh]\nfile = "strip.msh"\n[groups.right]\nx = 2.0\n' + BODY.replace('nodes = "tip"', 'nodes = "tipp"')
    (tmp_path / "s.toml").write_text(text)
    with pytest.raises(ValueError, match=r"\[\[load\]\] 1: nodes: mesh 'strip.msh' has no node group 'tipp'; node "
                       r"groups: \['body', 'clamp', 'tip', 'top'\].*; \[groups\] defines: right\.$"):
        read_scene_file(tmp_path / "s.toml")
    (tmp_path / "s.toml").write_text(text.replace("[groups.right]", "[groups.tip]"))
    with pytest.raises(ValueError, match=r"\[groups.tip\]: the mesh file already has a node group 'tip'"):
        read_scene_file(tmp_path / "s.toml")
    (tmp_path / "s.toml").write_text(text.replace('"strip.msh"', '"other.msh"'))
    with pytest.raises(ValueError, match=r"s.toml: \[mesh\]: file: mesh file '.*other.msh' does not exist"):
        read_scene_file(tmp_path / "s.toml")


@pytest.mark.parametrize("argv_tail,text,needle", [
    ([], STRIP.replace('nodes = "tip"', 'nodes = "tipp"'), "[[load]] 1: nodes: no node group 'tipp'"),
    ([], STRIP.replace("[[load]]", "[[loads]]"), "unknown table [loads]"),
    (["--mesh", "x.msh"], STRIP, "--mesh cannot be given with a scene file"),
    (["--lam", "1.0"], STRIP, "--lam cannot be given with a scene file"),
    (["--t-end", "0.5", "--schedule", "0.3:0.1"], STRIP, "--schedule '0.3:0.1' ends at t = 0.3, before --t-end 0.5"),
])
def test_cli_bad_scene_writes_nothing(argv_tail, text, needle, tmp_path, capsys):
    (tmp_path / "s.toml").write_text(text)
    out = tmp_path / "out" / "r.h5"
    assert main(["run", str(tmp_path / "s.toml"), "--out", str(out), "--quiet"] + argv_tail) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("jaxvisco: error: ") and needle in err, err
    assert sorted(os.listdir(tmp_path)) == ["s.toml"]  # no results file, here or in out/


def test_cli_options_override_the_file(tmp_path):
    """Flags given on the command line win; the others come from the scene file."""
    from jaxvisco.cli._main import _scene_file_options, build_parser

    (tmp_path / "s.toml").write_text(STRIP.replace("[time]", "[time]\nmax_halvings = 4"))
    args = build_parser().parse_args(["run", str(tmp_path / "s.toml")])
    sf, _ = _scene_file_options(args)
    assert (args.integrator, args.order, args.dt, args.schedule, args.t_end) == ("eG", 1, 0.1, None, 0.3)
    assert (args.out, args.chunk, args.commit_every, args.max_halvings) == (str(tmp_path / "strip.h5"), 3, 0.0, 4)
    assert args.scene_source == sf.source and args.scene_dir == str(tmp_path)
    args = build_parser().parse_args(["run", str(tmp_path / "s.toml"), "--integrator", "cG", "--order", "2",
                                      "--schedule", "0.2:0.1,0.5:0.05", "--out", "x.h5", "--chunk", "7",
                                      "--save-gamma", "--max-halvings", "2"])
    _scene_file_options(args)
    assert (args.integrator, args.order, args.dt, args.schedule, args.t_end) == ("cG", 2, None, "0.2:0.1,0.5:0.05",
                                                                               0.5)
    assert (args.out, args.chunk, args.save_gamma, args.max_halvings) == ("x.h5", 7, True, 2)


def test_cli_resume_refuses_a_scene_file(strip_run, capsys):
    d, _, _ = strip_run
    assert main(["run", str(d / "strip.toml"), "--resume", str(d / "strip.h5")]) == 2
    assert "with --resume the scene comes from the results file" in capsys.readouterr().err


def test_plot_of_a_loaded_run_balances_the_work(strip_run):
    """`jaxvisco plot` of a clamped, loaded run: the balance panel includes the external
    work (the body starts at rest: H0 = 0, so the scale is the work, not H0) and stays at
    rounding; the momentum panels say that loads and supports act."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxvisco.cli._main import plot_figure

    _, cli, _ = strip_run
    fig = plot_figure(cli)
    try:
        axes = {a.get_title(): a for a in fig.axes}
        err = axes["energy balance error |H + D − W − H0| / max(|H|, |W|)"].get_lines()[0].get_ydata()
        assert np.max(err) < 1e-8
        assert "linear momentum L − L(0) (loads, supports act)" in axes
    finally:
        plt.close(fig)
