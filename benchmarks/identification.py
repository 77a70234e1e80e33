"""Identification accuracy and cost together (issue #60): the 3D specimen's relaxation and
cyclic tests (grip force; in relaxation also a marker's lateral displacement), synthetic
data from (eta_dev, eta_vol, mu_neq) = (2, 5, 2), fitted jointly by `jv.identify`.

    python benchmarks/identification.py [--seeds 50] [--chunk 5] [--elements 8,2,2] [--k 2]
        [--parts exact,serial,fd,cold,noise] [--cold 3] [--out identification.json]

Measures, in one process:
- exact data, starts off by a factor 3 (up, down, up): errors, evaluations, the wall time
  of the first fit (compiling) and of a second one (compiled), the experiments evaluated
  in threads as `jv.identify` does; `serial`: the same fit as one program, one thread
  (its first fit reuses what the threaded fit traced of the inner programs);
- 1 % noise on every column (relative to its RMS), `--seeds` seeds fitted as one batch
  (`jv.identify_batch` on chunks of `--chunk` seeds, one after the other on this machine's
  device; one compilation, the chunks report as they finish): the errors, and
  how often each 95 % interval holds the true value (its coverage), with a binomial 95 %
  range for that fraction;
- `cold`: the first fit in each of `--cold` fresh processes (this script, part `first`),
  which trace and compile everything the fit runs: the issue's "a whole fit" (median);
- the same exact-data fit with a Jacobian by forward finite differences (one more run
  per parameter, as FEBio's and MatCal's optimizers do): evaluations and time, the ratio
  to beat.
"""

import argparse
import json
import os
import subprocess
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.stats  # noqa: E402

import jaxvisco as jv  # noqa: E402
from jaxvisco._tools import _identify  # noqa: E402

TRUTH = {"eta_dev": 2.0, "eta_vol": 5.0, "mu_neq": 2.0}
START = {"eta_dev": 6.0, "eta_vol": 5.0 / 3.0, "mu_neq": 6.0}


def experiments(elements=(8, 2, 2), k=2):
    """eG(k) runs (forces of eG(1) are step means, first order in h: k = 2 by default)."""
    out = []
    for test, kw in (("relaxation", dict(t1=3.0)), ("cyclic", dict(frequency=1.0, cycles=2.0))):
        sp = jv.scenes.specimen(test, elements=elements, **kw)
        times = np.linspace(0.0, sp.t1, int(round(sp.t1 / 0.1)) + 1)
        observe = [jv.ReactionForce(sp.grip, "x")]
        if test == "relaxation":
            observe.append(jv.Displacement(sp.scene.mesh, [[20.0, 10.0, 5.0]], "y"))
        c = sum(o.columns for o in observe)
        proto = jv.Experiment(sp.scene, jv.eG(k), times, np.zeros((len(times), c)), observe, dt0=sp.dt0, name=test)
        data = np.asarray(jax.jit(lambda s, e=proto: e.model(e.run(s)))(jv.with_parameters(sp.scene, TRUTH)))
        out.append(jv.Experiment(sp.scene, jv.eG(k), times, data, observe, dt0=sp.dt0, name=test))
    return out


def errors(values, names):
    return {n: float(v / TRUTH[n] - 1.0) for n, v in zip(names, np.asarray(values))}


@jax.custom_jvp
def _fd_residuals(values, problem):
    return _identify._residuals(values, problem)


@_fd_residuals.defjvp
def _fd_jvp(primals, tangents):
    """J v by a forward difference (one more run per direction), in relative steps."""
    values, problem = primals
    dv, _ = tangents
    r = _identify._residuals(values, problem)
    eps = 1e-6 * jnp.linalg.norm(values) / jnp.maximum(jnp.linalg.norm(dv), 1e-300)
    return r, (_identify._residuals(values + eps * dv, problem) - r) / eps


def fit(exps, residual, serial=False):
    """One fit from START by `jv.least_squares`, the experiments as blocks (in threads,
    as `jv.identify` fits them) or, `serial`, as one residual (one program)."""
    keys = tuple(START)
    start = np.array([START[k] for k in keys])
    problem = _identify._Problem(tuple(exps), keys)
    if serial:
        residuals, args = residual, problem
    else:
        residuals, args = _identify._by_experiment(problem)
        residuals = (residual,) * len(residuals)
    t = time.perf_counter()
    res = jv.least_squares(residuals, start, args, lower=np.zeros(3), names=keys, max_steps=50)
    jax.block_until_ready(res.values)
    return res, time.perf_counter() - t


def main(argv=None):
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from common import machine, write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--elements", default="8,2,2", help="the specimen's elements along x, y, z")
    ap.add_argument("--k", type=int, default=2, help="the time element eG(k)")
    ap.add_argument("--chunk", type=int, default=5, help="seeds per identify_batch call")
    ap.add_argument("--parts", default="exact,serial,fd,cold,noise",
                    help="exact: AD fits; serial: the compiled fit as one program; fd: finite differences; "
                         "cold: first fits in fresh processes; first: one first fit, printed as JSON")
    ap.add_argument("--cold", type=int, default=3, help="fresh processes of the part cold")
    ap.add_argument("--out", default="identification.json")
    args = ap.parse_args(argv)
    info = machine()
    elements = tuple(int(v) for v in args.elements.split(","))
    parts = args.parts.split(",")
    exps = experiments(elements, args.k)
    out = dict(machine=info, truth=TRUTH, start=START, elements=list(elements), integrator=f"eG({args.k})",
               m=int(sum(np.asarray(e.data).size for e in exps)))
    if parts == ["first"]:
        _, t_first = fit(exps, _identify._residuals)
        print(json.dumps(dict(first_fit_s=t_first)))
        return None
    if "exact" not in parts:
        return _noise(args, exps, out) if "noise" in parts else write_json(args.out, out)
    # exact data, AD Jacobian (forward mode through the runs)
    first, t_first = fit(exps, _identify._residuals)
    second, t_second = fit(exps, _identify._residuals)
    out["exact"] = dict(errors=errors(second.values, second.names), evaluations=int(second.iterations),
                        message=second.message, first_fit_s=t_first, compiled_fit_s=t_second)
    print(out["exact"], flush=True)
    if "serial" in parts:
        _, t_first_serial = fit(exps, _identify._residuals, serial=True)
        _, t_serial = fit(exps, _identify._residuals, serial=True)
        out["exact"].update(serial_first_fit_s=t_first_serial, serial_compiled_fit_s=t_serial,
                            threads_speedup_compiled=t_serial / t_second)
        print(out["exact"], flush=True)
    if "fd" in parts:
        _fd(exps, out, t_first, t_second)
    if "cold" in parts:
        cold = [_cold(args) for _ in range(args.cold)]
        out["exact"].update(cold_fit_s=float(np.median(cold)), cold_fit_all_s=cold)
        print(out["exact"], flush=True)
    if "noise" in parts:
        return _noise(args, exps, out)
    write_json(args.out, out)


def _cold(args):
    """The first fit's wall time in a fresh process (this script, part `first`)."""
    cmd = [sys.executable, os.path.abspath(__file__), "--parts", "first", "--elements", args.elements,
           "--k", str(args.k)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])["first_fit_s"]


def _fd(exps, out, t_first, t_second):
    """The exact-data fit with a finite-difference Jacobian."""
    _, fd_first = fit(exps, _fd_residuals)
    fd, fd_second = fit(exps, _fd_residuals)
    out["finite_differences"] = dict(errors=errors(fd.values, fd.names), evaluations=int(fd.iterations),
                                     first_fit_s=fd_first, compiled_fit_s=fd_second,
                                     ratio_compiled=fd_second / t_second, ratio_first=fd_first / t_first)
    print(out["finite_differences"], flush=True)


def _noise(args, exps, out):
    """1 % noise, `args.seeds` seeds as one batch."""
    from common import write_json

    rng = np.random.default_rng(0)
    batch = []
    for e in exps:
        d = np.asarray(e.data)
        batch.append(d[None] + 0.01 * np.sqrt(np.mean(d**2, axis=0)) * rng.standard_normal((args.seeds,) + d.shape))
    chunks, chunk_s = [], []
    t = time.perf_counter()
    for lo in range(0, args.seeds, args.chunk):
        part = [d[lo:lo + args.chunk] for d in batch]
        r = jv.identify_batch(exps, START, part)
        jax.block_until_ready(r.values)
        chunks.append(r)
        chunk_s.append(time.perf_counter() - t - sum(chunk_s))
        print(f"seeds {lo}..{lo + len(part[0]) - 1}: {time.perf_counter() - t:.1f} s", flush=True)
    t_batch = time.perf_counter() - t
    res = jax.tree.map(lambda *xs: np.concatenate(xs) if isinstance(xs[0], (np.ndarray, jax.Array)) else xs[0],
                       *chunks)
    names = res.names
    values, intervals = np.asarray(res.values), np.asarray(res.intervals)
    truth = np.array([TRUTH[n] for n in names])
    covered = (intervals[..., 0] <= truth) & (truth <= intervals[..., 1])
    lo, hi = scipy.stats.binom.ppf([0.025, 0.975], args.seeds, 0.95) / args.seeds
    out["noise"] = dict(seeds=args.seeds, chunk=args.chunk, level=0.01, batch_s=t_batch,
                        per_fit_s=t_batch / args.seeds, chunk_s=chunk_s,
                        per_fit_compiled_s=(float(np.median(chunk_s[1:])) / args.chunk if len(chunk_s) > 1 else None),
                        coverage={n: float(covered[:, i].mean()) for i, n in enumerate(names)},
                        coverage_expected_range=[float(lo), float(hi)],
                        error_mean={n: float(np.mean(values[:, i] / truth[i] - 1)) for i, n in enumerate(names)},
                        error_std={n: float(np.std(values[:, i] / truth[i] - 1)) for i, n in enumerate(names)},
                        mean_relative_standard_error={n: float(np.mean(np.asarray(res.relative_errors)[:, i]))
                                                      for i, n in enumerate(names)},
                        evaluations_max=int(np.max(np.asarray(res.iterations))),
                        converged=int(np.sum(np.isin(np.asarray(res.status_code), [1, 2, 3, 4]))))
    print(out["noise"], flush=True)
    write_json(args.out, out)


if __name__ == "__main__":
    main()
