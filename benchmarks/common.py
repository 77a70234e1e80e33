"""Shared helpers of the benchmark scripts: scenes, machine description, timing, JSON."""

import json
import os
import pathlib
import platform
import statistics
import subprocess
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxvisco as jv  # noqa: E402
from jaxvisco.scenes._lshape import PAPER  # noqa: E402

RESULTS = pathlib.Path(__file__).parent / "results"

# How the numbers were taken (recorded in every results file with the load averages).
CONDITIONS = ("one benchmark process at a time on the 2-core machine, nothing else of ours running (see the "
              "load averages at start and end); identical runs still vary by up to ~1.4x over minutes (a shared "
              "VM), so medians of repeats are given where repeated; compile time = first call minus a timed call")


def schemes():
    """The integrators the benchmarks compare, by name."""
    return {"cG(1)": jv.cG(1), "cG(2)": jv.cG(2), "cG(3)": jv.cG(3), "eG(1)": jv.eG(1), "eG(2)": jv.eG(2),
            "eG(3)": jv.eG(3), "Newmark": jv.Newmark(), "Midpoint": jv.Midpoint()}


def lshape(dim=2, refinement=1, element=None, mass="lumped", viscous=True, lam=PAPER["lam"], mu=PAPER["mu"],
           eta_dev=PAPER["eta_dev"], eta_vol=PAPER["eta_vol"]):
    """The paper's L-shape (as `jaxvisco.scenes.lshape`) with a choice of mass matrix."""
    mesh = jv.lshape_mesh(dim=dim, refinement=refinement, cell_type=element)
    nh = jv.NeoHooke(lam=lam, mu=mu)
    material = jv.ReeseGovindjee(nh, jv.NeoHooke(lam=PAPER["lam"], mu=PAPER["mu"]) if viscous else None,
                                 eta_dev=eta_dev, eta_vol=eta_vol)
    X = mesh.points
    vT = jnp.asarray(PAPER["v_translation"], dtype=float)
    w = jnp.asarray(PAPER["omega"], dtype=float)
    if dim == 2:
        v0 = vT[:2] + w[2] * jnp.stack([-X[:, 1], X[:, 0]], axis=-1)
    else:
        v0 = vT + jnp.cross(w, X)
    return jv.Scene(mesh, material, PAPER["density"], velocities=v0, mass=mass)


def machine():
    model = platform.processor()
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        for line in out.splitlines():
            if line.startswith("Model name:"):
                model = line.split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return dict(cpu_model=model, cores=os.cpu_count(), platform=platform.platform(), python=platform.python_version(),
                jax=jax.__version__, date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                load_average_at_start=list(os.getloadavg()), conditions=CONDITIONS)


def timed(fn, repeats=3, budget_s=None):
    """Call `fn()` once (compile + run), then `repeats` more times; returns
    (result of the last call, first-call seconds, median of the timed calls, all times).
    With `budget_s`, stop repeating once the timed calls have used that much."""
    t0 = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
        if budget_s is not None and sum(times) > budget_s:
            break
    wall = statistics.median(times) if times else first
    return out, first, wall, times


def write_json(name, data, stamp_end=True):
    """Write `data` to results/`name`; `stamp_end`: record the load average now as the
    measurement's end (False for files derived from earlier measurements)."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    data = dict(data)
    if "machine" in data and stamp_end:
        data["machine"]["load_average_at_end"] = list(os.getloadavg())
    path = RESULTS / name
    path.write_text(json.dumps(data, indent=1, default=_default))
    print(f"wrote {path}", flush=True)
    return path


def _default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def rel(a, b):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))
