"""Cost of derivatives and of batches (issue: gradients, identification, batching).

    python benchmarks/gradients.py [--quick]

Measures on the 2D L-shape (refinement 1, eG(1), h = 0.1, Newton rtol 1e-10), each case
in a fresh subprocess so that its peak resident memory (ru_maxrss) is its own:
- reverse-mode gradient time / forward time (after compilation, median of 3) of the loss
  dissipated(T) + free_energy(T) with respect to (log eta_dev, log eta_vol), for N steps;
- peak memory of that gradient with the default checkpointing (segments of sqrt(frames))
  and with one segment (no checkpointing: every step's residuals stored);
- a vmapped batch of 8 runs against 8 sequential runs of the same compiled single run.
Writes benchmarks/results/gradients.json.
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))

WORKER = r"""
import json, resource, sys, time
import jax, jax.numpy as jnp, numpy as np, equinox as eqx
jax.config.update("jax_enable_x64", True)
import jaxvisco as jv
mode, n, ck = sys.argv[1], int(sys.argv[2]), sys.argv[3]
ck = None if ck == "auto" else int(ck)
scene = jv.scenes.lshape(dim=2, refinement=1)
h = 0.1

def median(f, reps=3):
    ts = []
    for _ in range(reps):
        t = time.perf_counter(); jax.block_until_ready(f()); ts.append(time.perf_counter() - t)
    return float(np.median(ts))

if mode == "grad":
    def loss(z):
        sc = jv.with_parameters(scene, {"eta_dev": jnp.exp(z[0]), "eta_vol": jnp.exp(z[1])})
        s = jv.simulate(sc, jv.eG(1), t1=n * h, dt0=h, adjoint=jv.RecursiveCheckpointAdjoint(checkpoint_every=ck))
        return s.dissipated[-1] + s.free_energy[-1]
    z = jnp.log(jnp.array([5e4, 1e4]))
    fwd, grad = eqx.filter_jit(loss), eqx.filter_jit(jax.grad(loss))
    t = time.perf_counter(); jax.block_until_ready(fwd(z)); c_fwd = time.perf_counter() - t
    t = time.perf_counter(); jax.block_until_ready(grad(z)); c_grad = time.perf_counter() - t
    t_fwd, t_grad = median(lambda: fwd(z)), median(lambda: grad(z))
    out = dict(steps=n, checkpoint_every=ck, forward_s=t_fwd, gradient_s=t_grad, ratio=t_grad / t_fwd,
               first_call_forward_s=c_fwd, first_call_gradient_s=c_grad)
else:
    def run(eta):
        sc = jv.with_parameters(scene, {"eta_dev": eta})
        return jv.simulate(sc, jv.eG(1), t1=n * h, dt0=h).energy
    etas = jnp.linspace(2e4, 2e5, 8)
    single, batch = jax.jit(run), jax.jit(jax.vmap(run))
    jax.block_until_ready(single(etas[0])); jax.block_until_ready(batch(etas))
    t_seq = median(lambda: [single(e) for e in etas])
    t_batch = median(lambda: batch(etas))
    out = dict(steps=n, sequential_8_s=t_seq, batch_8_s=t_batch, speedup=t_seq / t_batch)
out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print("RESULT" + json.dumps(out))
"""


def case(*args):
    out = subprocess.run([sys.executable, "-c", WORKER, *map(str, args)], capture_output=True, text=True)
    if out.returncode != 0:
        return dict(args=list(map(str, args)), error=out.stderr[-2000:])
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT")][-1]
    r = json.loads(line[6:])
    print(json.dumps(r), flush=True)
    return r


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="100 steps only (a few minutes)")
    args = ap.parse_args(argv)
    cases = [("grad", 100, "auto"), ("grad", 100, 100), ("batch", 50, "auto")]
    if not args.quick:
        cases = [("grad", 1000, "auto"), ("grad", 1000, 1000), ("batch", 100, "auto")]
    t0 = time.time()
    results = [case(*c) for c in cases]
    cpu = platform.processor() or platform.machine()
    try:
        cpu = [ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")][0]
    except (OSError, IndexError):
        pass
    doc = dict(date=time.strftime("%Y-%m-%d %H:%M"), machine=dict(cpu=cpu, cores=os.cpu_count()),
               quick=args.quick, wall_s=time.time() - t0, results=results,
               note="no checkpointing = checkpoint_every equal to the number of frames (one segment); "
                    "every step's factorization stays cached until the backward sweep reaches it")
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    path = os.path.join(HERE, "results", "gradients_quick.json" if args.quick else "gradients.json")
    with open(path, "w") as f:
        json.dump(doc, f, indent=2)
    print("wrote", path)


if __name__ == "__main__":
    main()
