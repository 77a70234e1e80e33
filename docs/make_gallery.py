"""The examples gallery's pictures, made by the example scripts themselves.

    python docs/make_gallery.py            # every picture, full runs (a few minutes)
    python docs/make_gallery.py NAME ...   # some of them

`GALLERY` lists, for each example script, the arguments of its full run and of its short
run, where its picture appears and the name the gallery gives it; `tests/test_examples.py`
runs every script in its short mode and checks that it draws its picture, and that the
gallery page shows exactly these pictures.
"""

import importlib.util
import os
import shutil
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
EXAMPLES = os.path.join(HERE, os.pardir, "examples")
OUT = os.path.join(HERE, "gallery")

# name: (full-run arguments, short-run arguments, the picture the script writes); "{dir}"
# is a scratch folder, "{png}" the picture's path there.
GALLERY = {
    "lshape_paper": (["--out", "{dir}"], ["--quick", "--out", "{dir}"], "{dir}/energy.png"),
    "clamped_beam": (["--plot", "{png}"], ["--quick", "--plot", "{png}"], "{png}"),
    "lshape_3d": (["--plot", "{png}"], ["--quick", "--plot", "{png}"], "{png}"),
    "read_mesh": (["--steps", "100", "--plot", "{png}"], ["--steps", "3", "--plot", "{png}"], "{png}"),
    "identify_viscosity": (["--out", "{dir}"], ["--quick", "--out", "{dir}"], "{dir}/identify_fit.png"),
}


def load(name):
    spec = importlib.util.spec_from_file_location(name, os.path.join(EXAMPLES, name + ".py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def draw(name, short, folder):
    """Run example `name` (its short or full run) with its pictures in `folder`; returns
    the result of its `main` and the path of the picture it drew."""
    full_args, short_args, picture = GALLERY[name]
    fill = dict(dir=folder, png=os.path.join(folder, name + ".png"))
    args = [a.format(**fill) for a in (short_args if short else full_args)]
    result = load(name).main(args)
    return result, picture.format(**fill)


if __name__ == "__main__":
    os.makedirs(OUT, exist_ok=True)
    for name in sys.argv[1:] or GALLERY:
        with tempfile.TemporaryDirectory() as d:
            _, png = draw(name, False, d)
            shutil.copyfile(png, os.path.join(OUT, name + ".png"))
        print(f"docs/gallery/{name}.png")
