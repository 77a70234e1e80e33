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


# ------------------------------------------------------------------ the gallery
# The examples whose pictures the documentation's gallery shows (docs/make_gallery.py):
# each runs in its short mode and must draw its picture.
def _gallery():
    import importlib.util

    path = os.path.join(os.path.dirname(__file__), os.pardir, "docs", "make_gallery.py")
    spec = importlib.util.spec_from_file_location("make_gallery", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


GALLERY_NAMES = sorted(_gallery().GALLERY)


def test_gallery_scripts_draw_their_pictures_in_short_mode(tmp_path):
    """Each gallery script, short, draws its picture (the short runs of lshape_paper and
    identify_viscosity are `test_lshape_paper_quick`'s and
    `test_identify.py::test_identify_recovers_viscosities`', which check their pictures)."""
    gallery = _gallery()
    checked_elsewhere = {"lshape_paper": "{dir}/energy.png", "identify_viscosity": "{dir}/identify_fit.png"}
    for name, picture in checked_elsewhere.items():
        assert gallery.GALLERY[name][1:] == (["--quick", "--out", "{dir}"], picture), name
    for name in GALLERY_NAMES:
        if name in checked_elsewhere:
            continue
        folder = tmp_path / name
        folder.mkdir()
        _, png = gallery.draw(name, True, str(folder))
        assert os.path.getsize(png) > 10_000, (name, png)


def test_clamped_beam_from_its_scene_file():
    """The gallery's clamped beam (examples/scenes/beam2d.toml through read_scene_file):
    the load bends the tip down, and eG keeps H + D - H0 = W to the Newton tolerance."""
    sol, deflection = load("clamped_beam").main(["--quick"])
    H, D, W = (np.asarray(a) for a in (sol.energy, sol.dissipated, sol.external_work))
    assert sol.status == "done" and len(sol.step_t) == 10
    assert deflection[0] == 0.0 and deflection[-1] < -0.1
    assert np.max(np.abs(H - H[0] + D - W)) <= 1e-9 * np.max(W)
