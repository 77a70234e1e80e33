"""The examples run (short modes) and give sensible numbers."""

import importlib.util
import os

import numpy as np

EXAMPLES = os.path.join(os.path.dirname(__file__), os.pardir, "examples")


def load(name):
    spec = importlib.util.spec_from_file_location(name, os.path.join(EXAMPLES, name + ".py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_read_mesh():
    sol = load("read_mesh").main(["--steps", "3"])
    H = np.asarray(sol.energy)
    assert len(H) == 4 and np.all(np.diff(H) <= 0)
    assert abs(H[0] - 3111.93) < 0.01  # the mesh is the paper's L-shape


def test_lshape_3d_quick():
    sol = load("lshape_3d").main(["--quick"])
    H = np.asarray(sol.energy)
    assert sol.status == "done" and np.all(np.diff(H) <= 0)


def test_lshape_paper_quick(tmp_path):
    res = load("lshape_paper").main(["--quick", "--out", str(tmp_path)])
    t, H, status = res[("eG(1)", "large")]
    assert status == "done" and np.all(np.diff(H) <= 1e-9 * H[0])
    assert (tmp_path / "energy.png").exists()
