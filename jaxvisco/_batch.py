"""Batches of runs: `jax.vmap` on one device, split over devices with `jax.shard_map`.

A whole `simulate` call can be vmapped (over material parameters, initial velocities,
loads: anything that is an array in the scene): the compiled time loop then advances
all members together, each with its own Newton iterations and step control, and the
host factorizations run one member after the other. `sharded_map` splits the batch
across devices, each device running `vmap` on its share; because every member's
sparse factorization is a host callback, each device's program must own its callbacks,
which `shard_map` guarantees (a plain `jit` with sharded inputs would gather them).

Many hosts: start every process with `jax.distributed.initialize(...)` (coordinator
address, number of processes, process id); `jax.devices()` then lists the devices of all
hosts, and the same `sharded_map(fn, batch)` over a `Mesh` of all of them runs each host's
share there. Inputs must be placed with `jax.make_array_from_process_local_data` (each
host passes its own rows) and results read back per host (`addressable_shards`).
"""

from typing import Callable, Optional

import jax
import numpy as np
from jax.sharding import Mesh, PartitionSpec


def sharded_map(fn: Callable, *batch, devices: Optional[list] = None):
    """`jax.vmap(fn)(*batch)` with the batch split evenly over `devices` (default: all).

    **Arguments:** `fn` maps unbatched arrays (or pytrees) to a pytree of arrays;
    `batch`: arrays with a leading batch axis whose length is a multiple of the number
    of devices. **Returns:** the stacked outputs, sharded along the batch axis.
    """
    devices = jax.devices() if devices is None else list(devices)
    n = len(devices)
    sizes = {np.shape(x)[0] for x in jax.tree_util.tree_leaves(batch)}
    if len(sizes) != 1:
        raise ValueError(f"all batch inputs must share the leading axis length, got {sorted(sizes)}.")
    (size,) = sizes
    if size % n:
        raise ValueError(f"the batch size {size} is not a multiple of the number of devices {n}.")
    mesh = Mesh(np.asarray(devices), ("batch",))
    spec = PartitionSpec("batch")
    mapped = jax.shard_map(jax.vmap(fn), mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)
    return jax.jit(mapped)(*batch)
