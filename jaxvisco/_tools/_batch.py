"""Batches of runs: `jax.lax.map` or `jax.vmap` on one device, split over devices with
`jax.shard_map`.

A whole `simulate` call can be mapped over a batch (of material parameters, initial
velocities, loads: anything that is an array in the scene); each member keeps its own
Newton iterations and step control. Two ways, with very different costs:

- `jax.lax.map(run, batch)` (the default of `sharded_map`) runs the members one after
  the other inside one compiled program. Every member costs what a single run costs.
- `jax.vmap(run)(batch)` advances all members together. The solver's `lax.cond`s
  (re-form the tangent or not, run GMRES or only a line-search trial) then depend on
  batched values and become selects: every member pays for both branches on every
  Newton pass. On a 2-core CPU, 8 eG(1) runs of 20 steps took 2.8x as long as with
  `lax.map` (`benchmarks/batch_cost.py`); a finite-difference test over 12 eG(2) runs
  went from 565 s to 221 s when it switched to `lax.map`. Use vmap where the branches
  are cheap or the hardware is wide (a GPU).

`sharded_map` splits the batch across devices, each device mapping over its share; because every member's
sparse factorization is a host callback, each device's program must own its callbacks,
which `shard_map` guarantees (a plain `jit` with sharded inputs would gather them).

Many hosts: start every process with `jax.distributed.initialize(...)` (coordinator
address, number of processes, process id); `jax.devices()` then lists the devices of all
hosts, and the same `sharded_map(fn, batch)` over a `Mesh` of all of them runs each host's
share there. Inputs must be placed with `jax.make_array_from_process_local_data` (each
host passes its own rows) and results read back per host (`addressable_shards`).
"""

from typing import Any, Callable, Optional

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from .._config import jit


def sharded_map(fn: Callable, *batch, devices: Optional[list] = None, vectorize: bool = False) -> Any:
    """Map `fn` over a batch, split evenly over `devices` (default: all devices; with
    `jax.distributed.initialize()` in every process, those of all hosts).

    **Arguments:**

    - `fn`: maps unbatched arrays (or pytrees) to a pytree of arrays, e.g. a function
      that builds a scene from its arguments and returns a few numbers of its run. The
      compiled program is kept for later calls with the same `fn` (the same function
      object, or an `equinox.Module` of the same structure: its arrays are inputs of the
      program, not constants baked into it) and inputs of the same shapes.
    - `*batch`: arrays with a leading batch axis whose length is a multiple of the number
      of devices.
    - `devices`: the devices to use (default `jax.devices()`).
    - `vectorize`: False (default) runs each device's share one member after the other
      (`jax.lax.map`); True advances it together (`jax.vmap`), which on a CPU makes every
      member pay for every branch of the Newton solver (several times slower; the user
      guide's page on batches has the measurement).

    **Returns:**

    The stacked outputs, sharded along the batch axis.

    **Raises:**

    `ValueError` for batch inputs of different lengths or a length that is not a
    multiple of the number of devices; `TypeError` for a `vectorize` that is not a bool.

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import jaxvisco as jv

    scene = jv.scenes.lshape()

    def dissipated(eta_dev):
        s = jv.with_parameters(scene, {"eta_dev": eta_dev})
        return jv.simulate(s, jv.eG(1), t1=0.3, dt0=0.1).dissipated[-1]

    out = jv.sharded_map(dissipated, jnp.array([2e4, 5e4]))
    ```
    """
    if not isinstance(vectorize, bool):
        raise TypeError(f"vectorize must be True or False, got {vectorize!r}.")
    devices = jax.devices() if devices is None else list(devices)
    n = len(devices)
    sizes = {np.shape(x)[0] for x in jax.tree_util.tree_leaves(batch)}
    if len(sizes) != 1:
        raise ValueError(f"all batch inputs must share the leading axis length, got {sorted(sizes)}.")
    (size,) = sizes
    if size % n:
        raise ValueError(f"the batch size {size} is not a multiple of the number of devices {n}.")
    dynamic, static = eqx.partition(fn, eqx.is_array)
    return _mapped(dynamic, batch, static, tuple(devices), vectorize)


@jit
def _mapped(dynamic, batch, static, devices, vectorize):
    """`sharded_map`'s program: `fn`'s arrays (`dynamic`) replicated on every device, the
    batch split along its first axis. One compiled program per `fn` structure, devices
    and shapes (a program per call, with `fn`'s arrays as constants, cost the batch of fits
    of `identify_batch` its whole compile time again on every call), compiled with
    `compiler_options()` as jaxvisco's other top-level programs."""
    mesh = Mesh(np.asarray(devices), ("batch",))
    spec = PartitionSpec("batch")

    def per_device(dynamic, *b):
        fn = eqx.combine(dynamic, static)
        return jax.vmap(fn)(*b) if vectorize else jax.lax.map(lambda args: fn(*args), b)

    mapped = jax.shard_map(per_device, mesh=mesh, in_specs=(PartitionSpec(),) + (spec,) * len(batch), out_specs=spec,
                           check_vma=False)
    return mapped(dynamic, *batch)
