"""Ensembles over several devices: a batch of initial states split over a 1-D device
mesh, each device integrating its share with `jax.vmap` of `nhjax.integrate`."""

from collections.abc import Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, PyTree

from ._arguments import check_args, check_constraint_flag, check_method, check_step_counts, check_step_size, check_switch, state_dtype, trace_floats
from ._integrate import integrate
from ._solution import Solution
from ._results import result_codes, RESULTS, SUCCESS
from ._system import AbstractSystem


_AXIS = "batch"


def integrate_ensemble(
    system: AbstractSystem,
    method: diffrax.AbstractSolver,
    y0s: PyTree[Array],
    dt: float | Array,
    n_steps: int,
    args: PyTree = None,
    save_every: int = 1,
    throw: bool = True,
    *,
    t0: float | Array = 0.0,
    check_constraint: bool = True,
    devices: Sequence[jax.Device] | None = None,
    gather: bool = True,
) -> Solution:
    """`nhjax.integrate` for a batch of initial states, split over `devices`.

    `y0s` holds the states along a leading batch axis of every leaf (size `B`), and
    every trajectory shares `dt`, `n_steps`, `args` and `t0`. The batch is split over
    a 1-D mesh of `devices` (default: all of `jax.devices()`, so CPU devices, GPUs, or
    the devices of every host of a multi-process run) with `jax.shard_map`: each
    device runs `jax.vmap(nhjax.integrate)` on its own `B / D` states, its own time loop
    and root finds, with no communication between devices until the results are
    gathered. `B` need not be a multiple of `D`: the batch is padded with copies of its
    first state, whose results are dropped.

    Returns a `Solution` whose every field has the leading batch axis (sharded over the
    devices when `B` is a multiple of `D`); `result` holds one code per trajectory. A
    trajectory that fails does not spoil the others. With `throw=True` any failure
    raises a `RuntimeError` after the whole batch has run, naming the first failed
    trajectory; this check runs on the host, so under `jax.jit` or `jax.grad` pass
    `throw=False` and read each trajectory's `result`.

    With one device this is `jax.vmap` of `nhjax.integrate`; with several, the same
    computation divided among them. Results agree to rounding, not bit for bit: the
    size of each device's batch changes how XLA vectorises it.

    **Several processes** (a `jax.distributed` job: several hosts, or several processes
    on one machine, CPU ones with `jax_cpu_collectives_implementation="gloo"`): every
    process calls this with the same global batch `y0s` and the same other arguments;
    the devices of all processes share the batch. With `gather=True` (default) every
    process gets the whole `Solution` back as arrays it can read (gathered with
    `jax.experimental.multihost_utils.process_allgather`); with `gather=False` it gets
    the global arrays sharded over every process's devices, as the program left them
    (then `B` must be a multiple of `D`, and each process reads only its own shards).
    Not under a JAX transformation: the batch is put on the devices of every process
    from the host.

    The other arguments are those of `nhjax.integrate` (no progress meter: devices run
    their shares independently).
    """
    check_step_counts(n_steps, save_every)
    check_step_size(dt, t0)
    check_constraint_flag(check_constraint)
    check_switch("throw", throw)
    check_args(args)
    leaves = jax.tree.leaves(y0s)
    if not leaves or any(jnp.ndim(leaf) < 1 for leaf in leaves):
        raise ValueError("y0s must hold a batch of states: every leaf needs a leading batch axis.")
    size = jnp.shape(leaves[0])[0]
    if any(jnp.shape(leaf)[0] != size for leaf in leaves) or size == 0:
        raise ValueError(
            "Every leaf of y0s must have the same non-zero batch size along axis 0, got "
            f"{[jnp.shape(leaf)[0] for leaf in leaves]}."
        )
    try:
        system.check_shapes(jax.tree.map(lambda leaf: leaf[0], y0s), args)
    except ValueError as error:
        raise ValueError(f"Each state along y0s's leading batch axis: {error}") from error
    check_method(system, method)
    devices = checked_devices(jax.devices() if devices is None else devices)
    mesh = Mesh(np.asarray(devices), (_AXIS,))
    padded_size = -(-size // len(devices)) * len(devices)
    padded = jax.tree.map(
        lambda leaf: jnp.concatenate([leaf, jnp.repeat(leaf[:1], padded_size - size, axis=0)]),
        y0s,
    )
    sharding = NamedSharding(mesh, PartitionSpec(_AXIS))
    several_processes = any(device.process_index != jax.process_index() for device in devices)
    if several_processes:
        if padded_size != size and not gather:
            raise ValueError(
                f"integrate_ensemble(..., gather=False) across processes needs a batch size "
                f"that is a multiple of the {len(devices)} devices, got {size}."
            )
        padded = jax.tree.map(lambda leaf: _global_array(np.asarray(leaf), sharding), padded)
    else:
        padded = jax.device_put(padded, sharding)
    # dt, t0 and the check as arrays (dt and t0 in the states' dtype, as
    # `nhjax.integrate` casts them), so that runs differing in them share a program.
    dtype = state_dtype(y0s)
    solution = _sharded_run(
        system,
        method,
        padded,
        jnp.asarray(dt, dtype=dtype),
        jnp.asarray(t0, dtype=dtype),
        trace_floats(args),
        jnp.asarray(check_constraint, dtype=bool),
        mesh=mesh,
        n_steps=int(n_steps),
        save_every=int(save_every),
    )
    if several_processes and gather:
        solution = jax.tree.map(jnp.asarray, multihost_utils.process_allgather(solution, tiled=True))
    if padded_size != size:
        solution = jax.tree.map(lambda leaf: leaf[:size], solution)
    if throw:
        codes = solution.result
        if several_processes and not gather:
            codes = jax.tree.map(jnp.asarray, multihost_utils.process_allgather(codes, tiled=True))
        _raise_failures(codes)
    return solution


def checked_devices(devices: Sequence[jax.Device]) -> list[jax.Device]:
    """`devices` as a list, refused if empty or if a device is named twice."""
    devices = list(devices)
    if not devices:
        raise ValueError("devices must name at least one device.")
    if len(set(devices)) != len(devices):
        repeated = sorted({str(device) for device in devices if devices.count(device) > 1})
        raise ValueError(f"devices must be distinct (each takes its own share of the batch); repeated: {', '.join(repeated)}.")
    return devices


def _global_array(host: np.ndarray, sharding: NamedSharding) -> jax.Array:
    """The array `host`, which every process holds whole, split over the devices of
    every process: each process puts its own devices' shards."""
    return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])


def _raise_failures(result: RESULTS) -> None:
    """Raise, naming the first failed trajectory and its failure, if any failed. Done on
    the host: a runtime error inside the sharded program would stop one device while
    the others wait for it."""
    codes = result_codes(result)
    if isinstance(codes, jax.core.Tracer):
        raise ValueError(
            "integrate_ensemble(..., throw=True) checks the results on the host, so it "
            "cannot run under a JAX transformation (jit, grad, vmap); pass throw=False "
            "and read Solution.result."
        )
    codes = np.asarray(codes)
    failed = np.flatnonzero(codes != SUCCESS)
    if failed.size:
        first = int(failed[0])
        raise RuntimeError(
            f"{failed.size} of {codes.size} trajectories failed; trajectory {first}: "
            f"{RESULTS[jax.tree.map(lambda code: code[first], result)]}"
        )


@eqx.filter_jit
def _sharded_run(system, method, y0s, dt, t0, args, check_constraint, *, mesh, n_steps, save_every):
    # shard_map takes arrays only; the rest of args is closed over.
    arrays, static = eqx.partition(args, eqx.is_array)

    def run_share(y0s, dt, t0, arrays, check_constraint):
        share_args = eqx.combine(arrays, static)
        return jax.vmap(
            lambda y0: integrate(
                system, method, y0, dt, n_steps, share_args, save_every,
                throw=False, t0=t0, check_constraint=check_constraint,
            )
        )(y0s)

    replicated = PartitionSpec()
    return jax.shard_map(
        run_share,
        mesh=mesh,
        in_specs=(PartitionSpec(_AXIS), replicated, replicated, replicated, replicated),
        out_specs=PartitionSpec(_AXIS),
        check_vma=False,
    )(y0s, dt, t0, arrays, check_constraint)
