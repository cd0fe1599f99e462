"""Long runs that survive interruption: `nhjax.integrate` chunk by chunk, each finished
chunk written to disk at once, and a rerun continuing after the last chunk written."""

import math
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ._chunk_files import (
    chunk_arrays,
    chunk_path,
    computation_fingerprint,
    describe,
    failures,
    fingerprint,
    FORMAT,
    join_chunks,
    load_verified,
    open_run,
    run_id,
    run_lock,
    with_identity,
    write_atomically,
)
from ._arguments import check_args, check_method, check_step_counts, check_step_size, check_switch, trace_floats
from ._ensemble import checked_devices, integrate_ensemble
from ._integrate import integrate
from ._solution import Solution
from ._results import SUCCESS
from ._system import is_int


# About this many trajectory-steps per chunk by default: a second or so of the slower
# methods' work, so that an interruption loses little.
_DEFAULT_CHUNK_WORK = 50_000


def run_chunked(
    system,
    method,
    y0,
    dt,
    n_steps,
    *,
    directory,
    args=None,
    save_every=1,
    chunk_steps=None,
    progress=True,
    throw=True,
    devices=None,
) -> Solution:
    r"""`nhjax.integrate(system, method, y0, dt, n_steps, args, save_every)` run in
    chunks of `chunk_steps` steps, each written to `directory` as it finishes, so that
    an interrupted run goes on where it stopped when called again.

    Chunk $c$ takes the steps $cN_c$ to $\min((c + 1)N_c, N)$ from
    $t_0 = cN_c h$, starting from the last state of chunk $c - 1$. When it finishes,
    `directory/chunk_0000c.npz` receives its saves (`ts`, the leaves of `ys` as
    `y_0, y_1, ...`, `energy`, `constraint`, for a forced system `work` and
    `dissipated` counted from the chunk's start, `result`, and the `stats` as
    `stats_*`),
    written to a temporary file and renamed, so that a chunk file that exists is
    complete. Each chunk file also records what identifies it: the run's fingerprint
    (a hash of the manifest below), its index and step range, a fingerprint of the state
    it started from, and a checksum of its arrays. `chunk_steps` is a multiple of
    `save_every`, so the last save of a chunk
    is its final state, the state the next chunk starts from. Chunk 0 keeps the initial
    save; the others leave out their first save, which is the previous chunk's last.

    **Resuming.** `directory/manifest.json` records the run: the system and method
    (type and fields, functions by qualified name), a fingerprint of what the system's
    functions compute (`computation`: their program, so that an edited body under the
    same name is caught), fingerprints of `y0` and `args`,
    `dt`, `n_steps`, `save_every`, `chunk_steps`, the dtype and the batch size. A call
    whose run differs raises a `ValueError` naming what differs; otherwise the chunks on
    disk are loaded and the run continues after the last of them. Each chunk is
    verified as it is loaded: a file that cannot be read (truncated, empty), whose
    arrays do not match its checksum (corrupted), that belongs to another run or to
    another place in this one (copied or renamed), or that starts from another state
    than the end of the chunk before it, is never used: a `RuntimeWarning` names the
    file and the reason, and the chunk is computed again (it is derived data; its
    recomputation is bit-identical to an uninterrupted run). A missing chunk is
    computed again too. One process at a time per directory: a run holds a lock on it
    (`fcntl.flock` on `directory/.lock`, where the platform has it), and a second one
    raises a `RuntimeError` naming the directory.

    **What a chunk boundary does.** Each chunk starts the method afresh from the saved
    state $(q, p)$: solver state (such as a root finder's starting guess) is not carried
    across a boundary. So a chunked run is bit-for-bit the same as any other chunked
    run with the same `chunk_steps`, interrupted or not, and equals an unchunked
    `nhjax.integrate` run to roundoff only. A forced run's ledger restarts at each
    boundary and is summed across them when the chunks are joined.

    **Compilation.** One program runs every full chunk (`y0` and the chunk's `t0` are
    traced); a shorter last chunk compiles a second one. The default `chunk_steps` is
    about 50 000 steps divided by the batch size, rounded to a multiple of `save_every`
    and evened out over the chunks, so that the last chunk is as long as the others
    wherever the numbers allow.

    **Batches.** `y0` may hold a batch of states along a leading axis (every leaf one
    dimension more than a state of `system`): each chunk is then one `jax.vmap`ped
    program, and every array of the `Solution` has the batch axis first, as from
    `jax.vmap(nhjax.integrate)`. Where `devices` (default: `jax.local_devices()`, this
    process's) holds more than one device, each chunk is split over them as
    `nhjax.integrate_ensemble` splits a batch: each device runs its share at the same
    time, so a machine's cores or GPUs share the work (a CPU gives XLA one device per
    core when asked, as the `nhjax` command does). The split changes rounding (each
    device's batch is vectorised at its own size), so the manifest then records the
    number of devices, and a run is resumed only on as many; on one device the manifest
    and the numbers are those of a plain `vmap`. A single trajectory runs on the
    default device whatever `devices` holds.

    **Failures.** A chunk whose result is not successful (for a batch: for any
    trajectory) is written like the others, so that a rerun reports the failure at once
    (delete `directory` to compute it again). With `throw=True` it raises a
    `RuntimeError` naming the chunk, its time span and the `nhjax.RESULTS` message. With
    `throw=False` a single trajectory stops there: the `Solution` holds the saves before
    the failure, then NaN, as `nhjax.integrate` does, and the failure's code. A batch
    with `throw=False` runs on, as under `jax.vmap(nhjax.integrate)`: a failed
    trajectory holds NaN from its failure on and the code of its first failure.

    **Arguments:** those of `nhjax.integrate` (`t0` is 0), and

    - `directory`: where the manifest and chunks go; created if missing.
    - `chunk_steps`: steps per chunk, a positive multiple of `save_every` (at most
        `n_steps` are used); `None` for the default above.
    - `progress`: a tqdm bar over the steps, advanced chunk by chunk.
    - `devices`: the devices a batch's chunks are split over (see **Batches**).

    Returns the `Solution` of the whole run, the chunks' saves concatenated; its `stats`
    add up over the chunks (`max_root_find_steps` is the largest of them).
    """
    check_step_counts(n_steps, save_every)
    if isinstance(dt, jax.core.Tracer) or jnp.ndim(dt) != 0:
        raise ValueError("dt must be a concrete scalar: a chunked run cannot be traced.")
    check_step_size(dt)
    check_switch("throw", throw)
    check_switch("progress", progress)
    check_args(args)
    n_steps, save_every = int(n_steps), int(save_every)
    y0 = jax.tree.map(jnp.asarray, y0)
    batch = _batch_size(system, y0, args)
    check_method(system, method)
    if chunk_steps is None:
        chunk_steps = _default_chunk_steps(n_steps, save_every, batch)
    elif (
        not is_int(chunk_steps)
        or chunk_steps < 1
        or chunk_steps % save_every != 0
    ):
        raise ValueError(
            f"chunk_steps must be a positive multiple of save_every={save_every}, got "
            f"{chunk_steps!r}."
        )
    chunk_steps = min(int(chunk_steps), n_steps)
    leaves, treedef = jax.tree.flatten(y0)
    dtype = jnp.result_type(*leaves)
    directory = pathlib.Path(directory)
    manifest = dict(
        format=FORMAT,
        system=describe(system),
        computation=computation_fingerprint(system, y0 if batch is None else jax.tree.map(lambda leaf: leaf[0], y0), args),
        method=describe(method),
        initial_state=fingerprint(y0),
        args=fingerprint(args),
        dt=float(dt),
        n_steps=n_steps,
        save_every=save_every,
        chunk_steps=chunk_steps,
        dtype=str(dtype),
        batch=batch,
    )
    devices = checked_devices(jax.local_devices() if devices is None else devices)
    split = batch is not None and len(devices) > 1
    if split:
        manifest["devices"] = len(devices)
    with run_lock(directory):
        open_run(directory, manifest)
        run = run_id(manifest)

        n_chunks = math.ceil(n_steps / chunk_steps)
        time_axis = 0 if batch is None else 1
        dt = jnp.asarray(dt, dtype=dtype)
        traced_args = trace_floats(args)
        chunks = []
        state = leaves
        with tqdm(
            total=n_steps,
            unit="step",
            disable=not progress,
            desc=f"{type(method).__name__}, {n_chunks} chunk{'s' * (n_chunks > 1)}",
        ) as bar:
            for index in range(n_chunks):
                first_step = index * chunk_steps
                length = min(chunk_steps, n_steps - first_step)
                path = chunk_path(directory, index)
                identity = dict(
                    run=run, index=index, first_step=first_step, n_steps=length,
                    start=fingerprint(list(state)),
                )
                expected_saves = length // save_every + (index == 0)
                chunk = load_verified(path, identity, expected_saves, time_axis)
                if chunk is None:
                    # t0 = first_step * dt, exactly as nhjax.integrate spaces its steps.
                    t0 = dt * jnp.asarray(first_step, dtype=dtype)
                    start = jax.tree.unflatten(treedef, state)
                    if split:
                        solution = integrate_ensemble(
                            system, method, start, dt, length, traced_args, save_every, throw=False,
                            t0=t0, check_constraint=index == 0, devices=devices,
                        )
                    else:
                        solution = _run_chunk(
                            system, method, start, dt, t0, traced_args,
                            n_steps=length, save_every=save_every, batched=batch is not None,
                        )
                    chunk = chunk_arrays(solution, keep_first=index == 0, time_axis=time_axis)
                    stored = with_identity(chunk, identity)
                    write_atomically(path, lambda file: np.savez(file, **stored))
                chunks.append(chunk)
                bar.update(length)
                failed = chunk["result"] != SUCCESS
                if np.any(failed):
                    if throw:
                        span = (float(dt * first_step), float(dt * (first_step + length)))
                        raise RuntimeError(
                            f"Chunk {index + 1} of {n_chunks} (steps {first_step} to "
                            f"{first_step + length}, t = {span[0]:g} to {span[1]:g}) failed"
                            f"{failures(chunk['result'])} It is recorded in {path}; delete "
                            f"{directory} to run it again."
                        )
                    if batch is None:
                        break
                state = [np.take(chunk[f"y_{i}"], -1, axis=time_axis) for i in range(len(leaves))]
    return join_chunks(chunks, treedef, n_steps // save_every + 1, time_axis)


@eqx.filter_jit
def _run_chunk(system, method, y0, dt, t0, args, *, n_steps, save_every, batched):
    def run(y):
        # A later chunk starts from where the run got to: for a method that lets the
        # constraint drift (GONZALEZ-F) that state is off the constraint, as it should be.
        return integrate(
            system, method, y, dt, n_steps, args, save_every, throw=False, t0=t0, check_constraint=t0 == 0
        )

    return jax.vmap(run)(y0) if batched else run(y0)


def _batch_size(system, y0, args) -> int | None:
    """`None` for one state of `system`, else the size of the leading batch axis; the
    system's own shape error if `y0` is neither."""
    try:
        system.check_shapes(y0, args)
        return None
    except ValueError as error:
        sizes = {jnp.shape(leaf)[:1] for leaf in jax.tree.leaves(y0)}
        if len(sizes) != 1 or sizes == {()}:
            raise
        try:
            system.check_shapes(jax.tree.map(lambda leaf: leaf[0], y0), args)
        except ValueError:
            raise error from None
        return sizes.pop()[0]


def _default_chunk_steps(n_steps, save_every, batch) -> int:
    saves = n_steps // save_every
    target = max(1, _DEFAULT_CHUNK_WORK // ((batch or 1) * save_every))
    n_chunks = math.ceil(saves / target)
    return math.ceil(saves / n_chunks) * save_every
