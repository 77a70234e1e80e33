"""What a derivative of a run costs (issue #59): gradient / forward and jacfwd / forward
ratios, first calls in a fresh and in a cached process, peak memory.

    python benchmarks/gradient_cost.py [--cases t2,t10,...] [--out gradient_cost.json]

Loss (as in the issue): dissipated energy at the end + a position term,
``D(T) + 1e-3 mean |x(T) - X|^2``, of the paper's L-shape (2D r1, eG(1), h = 0.1, Newton
rtol 1e-10, default frames: every step) with respect to p parameters: (log eta_dev, log
eta_vol) for p = 2, plus (log mu, log lam) of the equilibrium branch for p = 4.

Every measurement runs in a fresh subprocess (its peak resident memory is its own):
- ``timing``: first calls of the jitted forward loss, `jax.grad` and `jax.jacfwd` (p = 2,
  then p = 4) in that order in one process, then medians of timed calls of each;
- ``first_grad``: the first `jax.grad` call alone in a fresh process, no cache;
- ``cached``: a process with the persistent cache on fills it with one gradient (timed: the
  first process), a second process's first gradient call is then timed (its own cache
  directory per case);
- ``cached_jacfwd``: the same for the first `jax.jacfwd` call (p = 2);
- ``memory``: peak RSS of a process that computes one gradient (and of one that computes
  only the forward loss).

Cases: t2, t10, t100 (20, 100, 1000 steps), t200_f20 (2000 steps, 20 frames), t1000_f10
(10 000 steps, 10 frames: memory), adaptive_t10 (PIDController 1e-6), hex8_r3 (3D L-shape
hex8, refinement 3: 12 000 position unknowns, 10 steps of eG(1) at h = 0.1).
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

WORKER = r"""
import json, os, resource, sys, time
import jax, jax.numpy as jnp, numpy as np, equinox as eqx
jax.config.update("jax_enable_x64", True)
import jaxvisco as jv
case, mode = sys.argv[1], sys.argv[2]
if mode in ("cached", "cached_jacfwd"):
    jv.enable_compilation_cache(sys.argv[3])
CASES = {
    "t2": dict(n=20), "t10": dict(n=100), "t100": dict(n=1000), "t200_f20": dict(n=2000, every=100),
    "t1000_f10": dict(n=10000, every=1000), "adaptive_t10": dict(n=100, adaptive=True),
    "hex8_r3": dict(n=10, dim=3, refinement=3, every=10),
}
c = CASES[case]
scene = jv.scenes.lshape(dim=c.get("dim", 2), refinement=c.get("refinement", 1))
h = 0.1
n = c["n"]
kw = dict(saveat=jv.SaveAt(every=c.get("every", 1)))
if c.get("adaptive"):
    kw = dict(stepsize_controller=jv.PIDController(rtol=1e-6, atol=1e-6), max_steps=1024)

def params(z):
    m = dict(eta_dev=jnp.exp(z[0]), eta_vol=jnp.exp(z[1]))
    if z.shape[0] > 2:
        m.update(mu=jnp.exp(z[2]), lam=jnp.exp(z[3]))
    return jv.with_parameters(scene, m)

def loss(z):
    s = jv.simulate(params(z), jv.eG(1), t1=n * h, dt0=h, **kw)
    return s.dissipated[-1] + 1e-3 * jnp.mean((s.x[-1] - scene.x0) ** 2)

mat = scene.material
z2 = jnp.log(jnp.array([mat.eta_dev, mat.eta_vol]))
eq = mat.equilibrium
z4 = jnp.concatenate([z2, jnp.log(jnp.array([eq.mu, eq.lam]))])
fwd, grad, jacfwd = eqx.filter_jit(loss), eqx.filter_jit(jax.grad(loss)), eqx.filter_jit(jax.jacfwd(loss))

def first(f, z):
    t = time.perf_counter(); out = jax.block_until_ready(f(z)); return time.perf_counter() - t, out

def median(f, z, reps, budget=60.0):
    ts = []
    for _ in range(reps):
        t = time.perf_counter(); jax.block_until_ready(f(z)); ts.append(time.perf_counter() - t)
        if sum(ts) > budget:
            break
    return float(np.median(ts)), ts

out = dict(case=case, mode=mode)
if mode == "timing":
    reps = int(sys.argv[3])
    out["first_forward_s"], value = first(fwd, z2)
    out["first_grad_s"], g = first(grad, z2)
    out["first_jacfwd2_s"], j2 = first(jacfwd, z2)
    out["first_jacfwd4_s"], j4 = first(jacfwd, z4)
    out["forward_s"], out["forward_all"] = median(fwd, z2, reps)
    out["grad_s"], out["grad_all"] = median(grad, z2, reps)
    out["jacfwd2_s"], out["jacfwd2_all"] = median(jacfwd, z2, reps)
    out["jacfwd4_s"], out["jacfwd4_all"] = median(jacfwd, z4, reps)
    out.update(grad_ratio=out["grad_s"] / out["forward_s"], jacfwd2_ratio=out["jacfwd2_s"] / out["forward_s"],
               jacfwd4_ratio=out["jacfwd4_s"] / out["forward_s"], loss=float(value), grad=np.asarray(g).tolist(),
               jacfwd2=np.asarray(j2).tolist(), grad_vs_jacfwd=float(jnp.max(jnp.abs(g - j2) / jnp.abs(g))))
elif mode in ("first_grad", "cached", "memory_grad"):
    out["first_grad_s"], g = first(grad, z2)
    out["grad"] = np.asarray(g).tolist()
elif mode == "cached_jacfwd":
    out["first_jacfwd2_s"], j = first(jacfwd, z2)
    out["jacfwd2"] = np.asarray(j).tolist()
elif mode in ("first_forward", "memory_forward"):
    out["first_forward_s"], v = first(fwd, z2)
out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
out["steps"] = n
print("RESULT" + json.dumps(out))
"""


def run(*args, env=None):
    p = subprocess.run([sys.executable, "-c", WORKER, *map(str, args)], capture_output=True, text=True, env=env)
    if p.returncode != 0:
        return dict(args=list(map(str, args)), error=p.stderr[-3000:])
    r = json.loads([ln for ln in p.stdout.splitlines() if ln.startswith("RESULT")][-1][6:])
    print(json.dumps({k: v for k, v in r.items() if not k.endswith("_all")}), flush=True)
    return r


def measure(case, reps, what):
    env = dict(os.environ, JAXVISCO_CACHE_DIR="off")
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    res = dict(case=case)
    if "timing" in what:
        res["timing"] = run(case, "timing", reps, env=env)
    if "first" in what:
        res["first_forward"] = run(case, "first_forward", env=env)
        res["first_grad"] = run(case, "first_grad", env=env)
    for mode in ("cached", "cached_jacfwd"):
        if mode in what:
            with tempfile.TemporaryDirectory() as d:
                res[f"{mode}_first_process"] = run(case, mode, d, env=env)  # fills the cache
                res[f"{mode}_second_process"] = run(case, mode, d, env=env)
    if "memory" in what:
        res["memory_forward"] = run(case, "memory_forward", env=env)
        res["memory_grad"] = run(case, "memory_grad", env=env)
    return res


DEFAULT = {"t2": ("timing", "first", "cached"), "t10": ("timing", "first", "cached"), "t100": ("timing",),
           "t200_f20": ("timing", "memory"), "t1000_f10": ("memory",), "adaptive_t10": ("timing",),
           "hex8_r3": ("timing",)}


def main(argv=None):
    from common import machine, write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(DEFAULT), help="comma-separated: " + ", ".join(DEFAULT))
    ap.add_argument("--what", default=None, help="override: timing,first,cached,cached_jacfwd,memory")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--out", default="gradient_cost.json")
    args = ap.parse_args(argv)
    info = machine()
    t0 = time.time()
    results = []
    for case in args.cases.split(","):
        what = args.what.split(",") if args.what else DEFAULT[case]
        results.append(measure(case, args.reps, what))
    write_json(args.out, dict(machine=info, wall_s=time.time() - t0, results=results))


if __name__ == "__main__":
    main()
