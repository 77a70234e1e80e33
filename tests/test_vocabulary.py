"""One vocabulary (issue #61): scene files and the command line take the Python names
(`t0`, `t1`, `dt0`, `[saveat]`, `[solver.gmres]`, `--t1`, `--dt0`, `--cell-type`), the
old names stay as deprecated aliases of the same run, `simulate(root_finder=)` replaces
`solver=`, and the Python helpers do what the scene files' tables do.

Compilation is the cost: every run here is the 4 x 1 strip or the paper's L-shape with
eG(1) at three steps, so the file compiles a few small programs."""

import os
import subprocess
import sys
import warnings

import numpy as np
import pytest
from helpers import subprocess_env

import jaxvisco as jv
from jaxvisco._scenefile._scenefile import read_quietly
from jaxvisco.cli import main
from jaxvisco.cli._main import build_parser, make_scene

STRIP = """
[mesh]
generator = "rectangle"
nx = 4
ny = 1
lx = 2.0
ly = 0.5

[groups.clamp]
x = 0.0

[groups.tip]
x = 2.0

[material]
lam = 300.0
mu = 75.0
eta_dev = 50.0
density = 1.0

[[dirichlet]]
nodes = "clamp"

[[load]]
nodes = "tip"
force = [0.0, -1.0]

[solver]
rtol = 1e-11
{solver}
{time}
{saveat}
[output]
chunk = 3
commit_every = 0
{output}
"""
NEW = dict(time="[time]\nt1 = 0.3\ndt0 = 0.1", saveat="[saveat]\nevery = 1\ngamma = true", output="",
           solver="[solver.gmres]\nmax_steps = 40\nrefresh_after = 3\nbackend = \"jaxvisco\"")
OLD = dict(time="[time]\nt_end = 0.3\ndt = 0.1", saveat="", output="save_every = 1\nsave_gamma = true",
           solver="krylov_max_steps = 40\nrefresh_after = 3\nkrylov = \"gmres\"")
# Each alias alone (the other keys new): the parts of the file it changes, the notes.
ALIASES = [
    (dict(time="[time]\nt_end = 0.3\ndt0 = 0.1"), ["[time]: t_end is deprecated, write t1"]),
    (dict(time="[time]\nt1 = 0.3\ndt = 0.1"), ["[time]: dt is deprecated, write dt0"]),
    (dict(saveat="[saveat]\nevery = 1", output="save_gamma = true"),
     ["[output]: save_gamma is deprecated, write [saveat] gamma"]),
    (dict(saveat="[saveat]\ngamma = true", output="save_every = 1"),
     ["[output]: save_every is deprecated, write [saveat] every"]),
    (dict(solver="krylov_max_steps = 40\n[solver.gmres]\nrefresh_after = 3"),
     ["[solver]: krylov_max_steps is deprecated, write [solver.gmres] max_steps"]),
    (dict(solver="refresh_after = 3\n[solver.gmres]\nmax_steps = 40"),
     ["[solver]: refresh_after is deprecated, write [solver.gmres] refresh_after"]),
    (dict(solver="krylov = \"gmres\"\n[solver.gmres]\nmax_steps = 40\nrefresh_after = 3"),
     ["[solver]: krylov is deprecated, write [solver.gmres] backend"]),
]


def strip_text(**parts):
    return STRIP.format(**{**NEW, **parts})


def settings(sf):
    """What a scene file sets for a run, besides the scene."""
    return (sf.integrator, sf.root_finder, sf.saveat, sf.t0, sf.t1, sf.dt0, tuple(sf.steps.ts), sf.max_halvings,
            sf.output["chunk"], sf.output["commit_every"])


def test_new_names_and_old_aliases_read_the_same_settings(tmp_path):
    """Every deprecated scene-file key sets what its new name sets, adds one note naming
    the replacement, and warns (FutureWarning) when read from Python."""
    (tmp_path / "new.toml").write_text(strip_text())
    new = read_quietly(tmp_path / "new.toml")
    assert new.deprecated == ()
    assert new.root_finder == jv.NewtonKrylov(rtol=1e-11, linear_solver=jv.GMRES(max_steps=40, refresh_after=3))
    assert new.saveat.every == 1 and new.saveat.gamma and (new.t0, new.t1, new.dt0) == (0.0, 0.3, 0.1)
    for i, (parts, notes) in enumerate(ALIASES):
        path = tmp_path / f"alias{i}.toml"
        path.write_text(strip_text(**parts))
        sf = read_quietly(path)
        assert settings(sf) == settings(new), parts
        assert sf.deprecated == tuple(f"{path}: {note}" for note in notes)
    (tmp_path / "old.toml").write_text(STRIP.format(**OLD))
    with pytest.warns(FutureWarning, match=r"\[time\]: t_end is deprecated, write t1") as caught:
        old = jv.read_scene_file(tmp_path / "old.toml")
    assert len([w for w in caught if issubclass(w.category, FutureWarning)]) == 7
    assert settings(old) == settings(new)
    with pytest.warns(DeprecationWarning, match=r"SceneFile.t_end is deprecated, use SceneFile.t1"):
        assert old.t_end == 0.3
    with pytest.warns(DeprecationWarning, match=r"SceneFile.solver is deprecated"):
        assert old.solver == new.root_finder


def test_old_and_new_scene_files_give_the_same_run(tmp_path, capsys):
    """`jaxvisco run` on the file of 0.1 names and on the file of new names: the same
    results, bit for bit; the old file's run prints one warning per deprecated key (after
    its options were accepted)."""
    (tmp_path / "new.toml").write_text(strip_text())
    (tmp_path / "old.toml").write_text(STRIP.format(**OLD))
    assert main(["run", str(tmp_path / "new.toml"), "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert main(["run", str(tmp_path / "old.toml"), "--quiet"]) == 0
    err = capsys.readouterr().err.splitlines()
    notes = [line for line in err if "is deprecated" in line]
    assert len(notes) == 7 and all(line.startswith("jaxvisco: warning: ") for line in notes), err
    a, b = jv.read_results(tmp_path / "new.h5"), jv.read_results(tmp_path / "old.h5")
    for key in ("t", "x", "p", "gamma", "energy", "external_work", "step_h"):
        np.testing.assert_array_equal(a[key], b[key])
    assert len(a["t"]) == 4 and a["gamma"].shape[0] == 4  # [saveat] every = 1, gamma = true


def test_unknown_keys_name_the_accepted_ones(tmp_path):
    for part, text, needle in [
        ("time", "[time]\nt1 = 0.3\ndt0 = 0.1\ntend = 1.0",
         "[time]: unknown key 'tend'; accepted: t0, t1, dt0, schedule, max_halvings, rtol, atol."),
        ("saveat", "[saveat]\nevry = 2", "[saveat]: unknown key 'evry'; accepted: every, gamma."),
        ("solver", "[solver.gmres]\nmaxsteps = 3", "[solver.gmres]: unknown key 'maxsteps'; accepted: max_steps, "
         "refresh_after, backend, preconditioner, restart, multigrid_precision."),
        ("output", "every = 2", "[output]: unknown key 'every'; accepted: file, chunk, commit_every."),
        ("time", "[time]\nt1 = 0.3\nt_end = 0.3\ndt0 = 0.1", "[time]: t_end: give t1 or the deprecated t_end, not "
         "both."),
        ("output", "save_every = 2", "[output]: save_every: give [saveat] every or the deprecated [output] "
         "save_every, not both."),
        ("solver", "krylov_max_steps = 3\n[solver.gmres]\nmax_steps = 3", "[solver]: krylov_max_steps: give "
         "[solver.gmres] max_steps or the deprecated [solver] krylov_max_steps, not both."),
        ("solver", "linear_solver = \"direct\"\n[solver.gmres]\nmax_steps = 3",
         "[solver.gmres] sets the Krylov solver, but linear_solver = 'direct'."),
        ("solver", "[solver.gmres]\nbackend = \"scipy\"",
         "[solver.gmres]: GMRES: backend must be one of ('jaxvisco', 'lineax'), got 'scipy'."),
        ("time", "[time]\nt0 = 1.0\nt1 = 0.5\ndt0 = 0.1", "[time]: t1: got 0.5; accepted: a time after t0 = 1.0."),
    ]:
        text = strip_text(**{part: text})
        (tmp_path / "s.toml").write_text(text)
        with pytest.raises(ValueError) as e:
            read_quietly(tmp_path / "s.toml")
        assert needle in str(e.value) and str(e.value).startswith(str(tmp_path / "s.toml")), str(e.value)


def test_scene_file_start_time_and_quadrature(tmp_path):
    """`[time] t0` starts the steps there; `[integrator] quadrature` is eG(k, quadrature=)."""
    text = strip_text(time="[time]\nt0 = 1.0\nt1 = 1.3\ndt0 = 0.1").replace("[solver]", "[integrator]\nname = "
                                                                                   "\"eG\"\norder = 2\nquadrature "
                                                                                   "= 4\n\n[solver]")
    (tmp_path / "s.toml").write_text(text)
    sf = read_quietly(tmp_path / "s.toml")
    np.testing.assert_allclose(sf.steps.ts, [1.0, 1.1, 1.2, 1.3], rtol=0, atol=1e-15)
    assert sf.integrator == jv.eG(2, quadrature=4)
    # the command line runs the file's integrator, its quadrature included (unless overridden)
    from jaxvisco.cli._options import _run_setup, _scene_file_options

    args = build_parser().parse_args(["run", str(tmp_path / "s.toml"), "--out", str(tmp_path / "s.h5")])
    sf, _ = _scene_file_options(args)
    assert _run_setup(args, sf, None)[0] == jv.eG(2, quadrature=4)
    args = build_parser().parse_args(["run", str(tmp_path / "s.toml"), "--order", "1", "--out", str(tmp_path / "s.h5")])
    sf, _ = _scene_file_options(args)
    assert _run_setup(args, sf, None)[0] == jv.eG(1)
    (tmp_path / "s.toml").write_text(text.replace('name = "eG"\norder = 2', 'name = "Midpoint"'))
    with pytest.raises(ValueError, match=r"\[integrator\]: quadrature: Midpoint has no quadrature"):
        read_quietly(tmp_path / "s.toml")


def test_command_line_new_names_and_old_spellings(tmp_path, capsys):
    """--t1/--t-end, --dt0/--dt, --cell-type/--element set the same options; an old
    spelling prints one note once the options are accepted, and messages about an option
    name it as it was written."""
    p = build_parser()
    new = p.parse_args(["run", "--t0", "0.0", "--t1", "0.3", "--dt0", "0.1", "--cell-type", "quad4"])
    old = p.parse_args(["run", "--t0", "0.0", "--t-end", "0.3", "--dt", "0.1", "--element", "quad4"])
    assert (new.t_end, new.dt, new.element) == (old.t_end, old.dt, old.element) == (0.3, 0.1, "quad4")
    assert new.deprecated is None
    assert old.deprecated == ["--t-end is deprecated, use --t1", "--dt is deprecated, use --dt0",
                              "--element is deprecated, use --cell-type"]
    args = ["--chunk", "3", "--commit-every", "0", "--quiet"]
    assert main(["run", "--t1", "0.3", "--dt0", "0.1", "--out", str(tmp_path / "new.h5")] + args) == 0
    assert "warning" not in capsys.readouterr().err
    assert main(["run", "--t-end", "0.3", "--dt", "0.1", "--out", str(tmp_path / "old.h5")] + args) == 0
    assert capsys.readouterr().err.splitlines() == ["jaxvisco: warning: --t-end is deprecated, use --t1.",
                                                    "jaxvisco: warning: --dt is deprecated, use --dt0."]
    a, b = jv.read_results(tmp_path / "new.h5"), jv.read_results(tmp_path / "old.h5")
    for key in ("t", "x", "energy"):
        np.testing.assert_array_equal(a[key], b[key])
    # an error names the option as written, and comes alone (no deprecation note)
    assert main(["run", "--t1", "inf", "--out", str(tmp_path / "x.h5")]) == 2
    assert capsys.readouterr().err.strip() == "jaxvisco: error: --t1 must be a finite time > 0, got inf."
    assert main(["run", "--t-end", "inf", "--out", str(tmp_path / "x.h5")]) == 2
    assert capsys.readouterr().err.strip() == "jaxvisco: error: --t-end must be a finite time > 0, got inf."


def test_run_mesh_asks_for_the_material_and_starts_at_rest(tmp_path, capsys):
    """`jaxvisco run --mesh` no longer gives a mesh the paper's material and spin: it asks
    for the material and starts the body at rest, or as --velocity/--angular-velocity say."""
    msh = os.path.join(os.path.dirname(__file__), os.pardir, "examples", "scenes", "beam2d.msh")
    assert main(["run", "--mesh", msh, "--out", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert "give the body's material: --lam, --mu, --density" in err and not (tmp_path / "x.h5").exists()
    scene = make_scene(mesh=msh, lam=300.0, mu=75.0, density=2.0)
    assert not np.asarray(scene.v0).any() and not scene.has_internal_variable
    moving = make_scene(mesh=msh, lam=300.0, mu=75.0, density=2.0, eta_dev=10.0, velocity="1,0", angular_velocity="0.5")
    X = np.asarray(moving.mesh.points)
    np.testing.assert_allclose(np.asarray(moving.v0), np.stack([1.0 - 0.5 * X[:, 1], 0.5 * X[:, 0]], -1), atol=1e-15)
    assert moving.has_internal_variable and float(moving.material.eta_dev) == 10.0
    with pytest.raises(ValueError, match=r"--angular-velocity must be 1 finite number separated by commas, got '1,2'"):
        make_scene(mesh=msh, lam=300.0, mu=75.0, density=2.0, angular_velocity="1,2")
    with pytest.raises(ValueError, match="--velocity and --angular-velocity set the initial motion of a --mesh body"):
        make_scene(velocity="1,0")


def test_root_finder_equals_the_deprecated_solver():
    scene = jv.scenes.lshape(dim=2, refinement=1)
    nk = jv.NewtonKrylov()  # the default: the program the examples compile
    new = jv.simulate(scene, jv.eG(1), t1=0.3, dt0=0.1, root_finder=nk)
    with pytest.warns(DeprecationWarning, match=r"solver= is deprecated, use root_finder="):
        old = jv.simulate(scene, jv.eG(1), t1=0.3, dt0=0.1, solver=nk)
    for field in ("t", "x", "p", "energy", "dissipated", "newton_iterations"):
        np.testing.assert_array_equal(np.asarray(getattr(old, field)), np.asarray(getattr(new, field)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        with pytest.raises(TypeError, match="give root_finder or the deprecated solver, not both"):
            jv.simulate(scene, jv.eG(1), t1=0.3, dt0=0.1, root_finder=nk, solver=nk)
    with pytest.raises(TypeError, match=r"root_finder must be NewtonKrylov\(...\), got 'newton'"):
        jv.simulate(scene, jv.eG(1), t1=0.3, dt0=0.1, root_finder="newton")


def test_python_helpers_equal_the_scene_file_tables(tmp_path):
    """`rigid_velocity`, `nodes_in` and `clamp` build what `[initial]`, `[groups]` and
    `[[dirichlet]]` build; `cell_type=` replaces `element=`."""
    text = """
[mesh]
generator = "box"
nx = 2
ny = 1
nz = 1
lx = 2.0
[groups.left]
x = 0.0
[groups.band]
x = [0.5, 1.0]
y = 0.0
[material]
lam = 10.0
mu = 5.0
density = 1.0
[initial]
velocity = [1.0, 0.0, 0.5]
angular_velocity = [0.0, 0.3, 2.0]
center = [1.0, 0.5, 0.5]
[[dirichlet]]
nodes = "left"
[[dirichlet]]
nodes = "band"
components = ["x", "z"]
[time]
t1 = 1.0
dt0 = 0.5
"""
    (tmp_path / "h.toml").write_text(text)
    s = read_quietly(tmp_path / "h.toml").scene
    mesh = jv.box(2, 1, 1, lx=2.0)
    fixed = jv.clamp(mesh, jv.nodes_in(mesh, x=0.0)) | jv.clamp(mesh, jv.nodes_in(mesh, x=(0.5, 1.0), y=0.0),
                                                              ["x", "z"])
    np.testing.assert_array_equal(s.fixed.array, fixed)
    v = jv.rigid_velocity(mesh, velocity=[1.0, 0.0, 0.5], angular_velocity=[0.0, 0.3, 2.0], center=[1.0, 0.5, 0.5])
    np.testing.assert_array_equal(np.asarray(s.v0), np.where(fixed, 0.0, v))
    paper = jv.scenes.lshape()
    np.testing.assert_array_equal(np.asarray(paper.v0), jv.rigid_velocity(paper.mesh, [6.0, 0.0], 0.6))
    # bad input names the value and what is accepted
    for call, needle in [
        (lambda: jv.nodes_in(mesh), "give at least one coordinate range"),
        (lambda: jv.nodes_in(jv.rectangle(2, 1), z=0.0), "the mesh is 2D; z is not a coordinate of it"),
        (lambda: jv.nodes_in(mesh, x=5.0), r"no node lies in the ranges given; the mesh spans x in \[0, 2\]"),
        (lambda: jv.nodes_in(mesh, x=(1.0, 0.0)), r"x must be a finite range with lo <= hi, got \(1.0, 0.0\)"),
        (lambda: jv.clamp(mesh, [0, 99]), r"nodes must be indices in \[0, 12\)"),
        (lambda: jv.clamp(jv.rectangle(2, 1), [0], "z"), "component 'z' of 'z' is not one of a 2D mesh"),
        (lambda: jv.rigid_velocity(mesh, angular_velocity=1.0), "angular_velocity must be 3 numbers in 3D"),
        (lambda: jv.rigid_velocity(mesh, velocity=[1.0, 0.0]), "velocity must be 3 numbers for a 3D body"),
        (lambda: jv.rigid_velocity(mesh, center=[0.0, 0.0, 0.0]), "a center needs an angular_velocity"),
    ]:
        with pytest.raises(ValueError, match=needle):
            call()
    with pytest.warns(DeprecationWarning, match=r"lshape_mesh\(\): element= is deprecated, use cell_type="):
        old = jv.lshape_mesh(2, 1, element="tri3")
    np.testing.assert_array_equal(np.asarray(old.cells), np.asarray(jv.lshape_mesh(2, 1, cell_type="tri3").cells))
    with pytest.warns(DeprecationWarning, match=r"lshape\(\): element= is deprecated"):
        assert jv.scenes.lshape(element="tri3").mesh.cell_type == "tri3"


def test_missing_extension_warns_once_with_the_fix(tmp_path):
    """Installed without the C++ extension, importing jaxvisco warns once, with the fix;
    with JAXVISCO_HOST_LU=callback (that path chosen) it does not."""
    (tmp_path / "sitecustomize.py").write_text(
        "import sys\n"
        "class _Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'jaxvisco._solver._ffi._hostlu':\n"
        "            raise ImportError('no extension')\n"
        "sys.meta_path.insert(0, _Block())\n")
    env = subprocess_env()
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path)] + [p for p in sys.path if p])
    env.pop("JAXVISCO_HOST_LU", None)
    code = "import jaxvisco, jaxvisco._solver._sparse as s; print(s.backend())"
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "callback"
    assert p.stderr.count("RuntimeWarning: jaxvisco was installed without its C++ extension (no extension)") == 1
    assert "install a C++ compiler (e.g. g++) and reinstall jaxvisco" in p.stderr
    env["JAXVISCO_HOST_LU"] = "callback"
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "RuntimeWarning" not in p.stderr, p.stderr


def test_fit_files_take_the_scene_file_names(tmp_path):
    """`jaxvisco identify`'s experiments are their scene files' runs in the Python names
    (t0, t1, dt0, [solver]); a scene file with the old [time] names gives the same
    experiment, with the deprecation note. Nothing is run."""
    from jaxvisco.cli._identify import read_fit_file

    scene = open(os.path.join(os.path.dirname(__file__), os.pardir, "examples", "fit", "relaxation.toml")).read()
    assert "t1 = 3.0" in scene and "dt0 = 0.05" in scene
    np.savetxt(tmp_path / "data.csv", np.column_stack([np.linspace(0.5, 3.0, 6), np.zeros(6)]), delimiter=",",
               header="time,force", comments="")
    fit = ('[parameters]\neta_dev = 6.0\n\n[[experiment]]\nscene = "{}"\ndata = "data.csv"\n\n'
           '[[experiment.observe]]\ncolumn = "force"\nreaction = "grip"\ncomponent = "x"\n')
    runs = {}
    for name, text in [("new", scene.replace("t1 = 3.0", "t0 = 0.5\nt1 = 3.0")),
                       ("old", scene.replace("t1 = 3.0", "t0 = 0.5\nt_end = 3.0").replace("dt0 = 0.05", "dt = 0.05")),
                       ("solver", scene.replace("t1 = 3.0", "t0 = 0.5\nt1 = 3.0") + "\n[solver]\nrtol = 1e-12\n")]:
        (tmp_path / f"{name}.toml").write_text(text)
        (tmp_path / f"{name}-fit.toml").write_text(fit.format(f"{name}.toml"))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            (e,), params, _, _ = read_fit_file(tmp_path / f"{name}-fit.toml")
        notes = [str(w.message) for w in caught if issubclass(w.category, FutureWarning)]
        assert ("t_end is deprecated, write t1" in " ".join(notes)) == (name == "old"), notes
        runs[name] = e
    for e in runs.values():
        assert (e.t0, e.t1, e.dt0) == (0.5, 3.0, 0.05)
        assert e.stepsize_controller == runs["new"].stepsize_controller
    assert runs["new"].root_finder.rtol == runs["old"].root_finder.rtol == 1e-11  # no [solver]: jv.Experiment's
    assert runs["solver"].root_finder.rtol == 1e-12
