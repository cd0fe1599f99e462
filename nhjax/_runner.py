"""Long runs that survive interruption: `nhjax.integrate` chunk by chunk, each finished
chunk written to disk at once, and a rerun continuing after the last chunk written."""

import hashlib
import json
import math
import numbers
import os
import pathlib
import tempfile
import warnings
import zipfile

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ._integrate import _trace_floats, check_args, check_step_counts, check_step_size, integrate, Solution
from ._results import RESULTS


# About this many trajectory-steps per chunk by default: a second or so of the slower
# methods' work, so that an interruption loses little.
_DEFAULT_CHUNK_WORK = 50_000
_MANIFEST = "manifest.json"
_FORMAT = 2
_SUMMED_STATS = ("num_steps", "root_find_steps", "substep_root_find_steps")


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
) -> Solution:
    r"""`nhjax.integrate(system, method, y0, dt, n_steps, args, save_every)` run in
    chunks of `chunk_steps` steps, each written to `directory` as it finishes, so that
    an interrupted run goes on where it stopped when called again.

    Chunk $c$ takes the steps $cN_c$ to $\min((c + 1)N_c, N)$ from
    $t_0 = cN_c h$, starting from the last state of chunk $c - 1$. When it finishes,
    `directory/chunk_0000c.npz` receives its saves (`ts`, the leaves of `ys` as
    `y_0, y_1, ...`, `energy`, `constraint`, `result`, and the `stats` as `stats_*`),
    written to a temporary file and renamed, so that a chunk file that exists is
    complete. Each chunk file also records what identifies it: the run's fingerprint
    (a hash of the manifest below), its index and step range, a fingerprint of the state
    it started from, and a checksum of its arrays. `chunk_steps` is a multiple of
    `save_every`, so the last save of a chunk
    is its final state, the state the next chunk starts from. Chunk 0 keeps the initial
    save; the others leave out their first save, which is the previous chunk's last.

    **Resuming.** `directory/manifest.json` records the run: the system and method
    (type and fields, functions by qualified name), fingerprints of `y0` and `args`,
    `dt`, `n_steps`, `save_every`, `chunk_steps`, the dtype and the batch size. A call
    whose run differs raises a `ValueError` naming what differs; otherwise the chunks on
    disk are loaded and the run continues after the last of them. Each chunk is
    verified as it is loaded: a file that cannot be read (truncated, empty), whose
    arrays do not match its checksum (corrupted), that belongs to another run or to
    another place in this one (copied or renamed), or that starts from another state
    than the end of the chunk before it, is never used: a `RuntimeWarning` names the
    file and the reason, and the chunk is computed again (it is derived data; its
    recomputation is bit-identical to an uninterrupted run). A missing chunk is
    computed again too. One process at a time per directory.

    **What a chunk boundary does.** Each chunk starts the method afresh from the saved
    state $(q, p)$: solver state (such as a root finder's starting guess) is not carried
    across a boundary. So a chunked run is bit-for-bit the same as any other chunked
    run with the same `chunk_steps`, interrupted or not, and equals an unchunked
    `nhjax.integrate` run to roundoff only.

    **Compilation.** One program runs every full chunk (`y0` and the chunk's `t0` are
    traced); a shorter last chunk compiles a second one. The default `chunk_steps` is
    about 50 000 steps divided by the batch size, rounded to a multiple of `save_every`
    and evened out over the chunks, so that the last chunk is as long as the others
    wherever the numbers allow.

    **Batches.** `y0` may hold a batch of states along a leading axis (every leaf one
    dimension more than a state of `system`): each chunk is then one `jax.vmap`ped
    program, and every array of the `Solution` has the batch axis first, as from
    `jax.vmap(nhjax.integrate)`.

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

    Returns the `Solution` of the whole run, the chunks' saves concatenated; its `stats`
    add up over the chunks (`max_root_find_steps` is the largest of them).
    """
    check_step_counts(n_steps, save_every)
    if isinstance(dt, jax.core.Tracer) or jnp.ndim(dt) != 0:
        raise ValueError("dt must be a concrete scalar: a chunked run cannot be traced.")
    check_step_size(dt)
    check_args(args)
    n_steps, save_every = int(n_steps), int(save_every)
    y0 = jax.tree.map(jnp.asarray, y0)
    batch = _batch_size(system, y0, args)
    if chunk_steps is None:
        chunk_steps = _default_chunk_steps(n_steps, save_every, batch)
    elif (
        not isinstance(chunk_steps, numbers.Integral)
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
        format=_FORMAT,
        system=_describe(system),
        method=_describe(method),
        initial_state=_fingerprint(y0),
        args=_fingerprint(args),
        dt=float(dt),
        n_steps=n_steps,
        save_every=save_every,
        chunk_steps=chunk_steps,
        dtype=str(dtype),
        batch=batch,
    )
    _open_run(directory, manifest)
    run = hashlib.sha256(json.dumps(manifest, sort_keys=True).encode()).hexdigest()[:16]

    n_chunks = math.ceil(n_steps / chunk_steps)
    time_axis = 0 if batch is None else 1
    dt = jnp.asarray(dt, dtype=dtype)
    traced_args = _trace_floats(args)
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
            path = directory / f"chunk_{index:05d}.npz"
            identity = dict(
                run=run, index=index, first_step=first_step, n_steps=length,
                start=_fingerprint(list(state)),
            )
            expected_saves = length // save_every + (index == 0)
            chunk = _load_verified(path, identity, expected_saves, time_axis)
            if chunk is None:
                # t0 = first_step * dt, exactly as nhjax.integrate spaces its steps.
                t0 = dt * jnp.asarray(first_step, dtype=dtype)
                solution = _run_chunk(
                    system, method, jax.tree.unflatten(treedef, state), dt, t0, traced_args,
                    n_steps=length, save_every=save_every, batched=batch is not None,
                )
                chunk = _chunk_arrays(solution, keep_first=index == 0, time_axis=time_axis)
                stored = _with_identity(chunk, identity)
                write_atomically(path, lambda file: np.savez(file, **stored))
            chunks.append(chunk)
            bar.update(length)
            failed = chunk["result"] != _SUCCESS
            if np.any(failed):
                if throw:
                    span = (float(dt * first_step), float(dt * (first_step + length)))
                    raise RuntimeError(
                        f"Chunk {index + 1} of {n_chunks} (steps {first_step} to "
                        f"{first_step + length}, t = {span[0]:g} to {span[1]:g}) failed"
                        f"{_failures(chunk['result'])} It is recorded in {path}; delete "
                        f"{directory} to run it again."
                    )
                if batch is None:
                    break
            state = [np.take(chunk[f"y_{i}"], -1, axis=time_axis) for i in range(len(leaves))]
    return _assemble(chunks, treedef, n_steps // save_every + 1, time_axis)


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


# Result codes go to disk as the integer inside the enumeration item, its only leaf.
_RESULT_TREEDEF = jax.tree.structure(RESULTS.successful)
_SUCCESS = int(jax.tree.leaves(RESULTS.successful)[0])


def _code(result) -> np.ndarray:
    return np.asarray(jax.tree.leaves(result)[0])


def _result(code) -> RESULTS:
    return jax.tree.unflatten(_RESULT_TREEDEF, [jnp.asarray(code)])


def _failures(codes) -> str:
    """': message.' for one trajectory; for a batch, which trajectories failed how."""
    codes = np.asarray(codes)
    if codes.ndim == 0:
        return f": {RESULTS[_result(codes)]}"
    lines = [
        f"\n  trajectories {np.flatnonzero(codes == code).tolist()}: {RESULTS[_result(code)]}"
        for code in np.unique(codes[codes != _SUCCESS])
    ]
    return "".join(lines) + "\n"


def _chunk_arrays(solution, *, keep_first, time_axis) -> dict[str, np.ndarray]:
    """A chunk's saves (without the first unless `keep_first`) and stats, as NumPy."""
    saves = dict(ts=solution.ts, energy=solution.energy)
    saves.update({f"y_{i}": leaf for i, leaf in enumerate(jax.tree.leaves(solution.ys))})
    if solution.constraint is not None:
        saves["constraint"] = solution.constraint
    start = 0 if keep_first else 1
    chunk = {
        name: np.take(np.asarray(array), np.arange(start, array.shape[time_axis]), axis=time_axis)
        for name, array in saves.items()
    }
    chunk["result"] = _code(solution.result)
    chunk.update(
        {f"stats_{name}": np.asarray(value) for name, value in solution.stats.items() if value is not None}
    )
    return chunk


_IDENTITY = ("run", "index", "first_step", "n_steps", "start")


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    """A hash of the names, dtypes, shapes and bytes of `arrays`."""
    digest = hashlib.sha256()
    for name in sorted(arrays):
        array = np.asarray(arrays[name])
        digest.update(f"{name}:{array.dtype.str}{array.shape}".encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def _with_identity(chunk: dict[str, np.ndarray], identity: dict) -> dict[str, np.ndarray]:
    """The arrays written for a chunk: its saves and stats, what identifies it, and a
    checksum of all of them."""
    stored = dict(chunk, **{f"chunk_{key}": np.asarray(value) for key, value in identity.items()})
    stored["checksum"] = np.asarray(_checksum(stored))
    return stored


def _load_verified(path: pathlib.Path, identity: dict, expected_saves: int, time_axis: int):
    """The chunk in `path` if it exists and is the chunk `identity` describes; `None`
    (after a warning naming the file and why, and deleting a bad file) if it must be
    computed."""
    if not path.exists():
        return None
    problem = None
    try:
        with np.load(path, allow_pickle=False) as data:
            stored = {name: data[name] for name in data.files}
    except (OSError, EOFError, ValueError, zipfile.BadZipFile, zipfile.LargeZipFile) as error:
        problem = f"cannot be read ({type(error).__name__}: {error})"
    else:
        checksum = stored.pop("checksum", None)
        found = {key: stored.get(f"chunk_{key}") for key in _IDENTITY}
        if checksum is None or any(value is None for value in found.values()):
            problem = "is not a chunk file of this format"
        elif str(checksum) != _checksum(stored):
            problem = "does not match its checksum (its contents are corrupted)"
        elif str(found["run"]) != identity["run"]:
            problem = "belongs to another run"
        elif (int(found["index"]), int(found["first_step"]), int(found["n_steps"])) != (
            identity["index"], identity["first_step"], identity["n_steps"]
        ):
            problem = (
                f"holds chunk {int(found['index'])} (steps {int(found['first_step'])} to "
                f"{int(found['first_step']) + int(found['n_steps'])}), not chunk "
                f"{identity['index']} (steps {identity['first_step']} to "
                f"{identity['first_step'] + identity['n_steps']})"
            )
        elif str(found["start"]) != identity["start"]:
            problem = "starts from another state than the end of the chunk before it"
        elif "ts" not in stored or stored["ts"].shape[time_axis] != expected_saves:
            problem = f"does not hold the {expected_saves} saves of this chunk"
    if problem is None:
        return {name: array for name, array in stored.items() if not name.startswith("chunk_")}
    warnings.warn(f"{path} {problem}: not used; computing the chunk again.", RuntimeWarning, stacklevel=3)
    path.unlink()
    return None


def _assemble(chunks, treedef, n_saved, time_axis) -> Solution:
    def joined(name):
        array = np.concatenate([chunk[name] for chunk in chunks], axis=time_axis)
        missing = n_saved - array.shape[time_axis]
        if missing:  # a single trajectory that stopped at a failed chunk
            padding = np.full((missing, *array.shape[1:]), np.nan, dtype=array.dtype)
            array = np.concatenate([array, padding])
        return jnp.asarray(array)

    result = chunks[0]["result"]
    for chunk in chunks[1:]:
        result = np.where(result == _SUCCESS, chunk["result"], result)
    stats = {}
    for name in _SUMMED_STATS:
        if f"stats_{name}" in chunks[0]:
            stats[name] = jnp.asarray(sum(chunk[f"stats_{name}"] for chunk in chunks))
        else:
            stats[name] = None
    stats["max_root_find_steps"] = (
        jnp.asarray(np.max([chunk["stats_max_root_find_steps"] for chunk in chunks], axis=0))
        if "stats_max_root_find_steps" in chunks[0]
        else None
    )
    if "stats_failed_substep" in chunks[0]:  # a composition: the substep of the first failure
        failed_substep = chunks[0]["stats_failed_substep"]
        for chunk in chunks[1:]:
            failed_substep = np.where(failed_substep < 0, chunk["stats_failed_substep"], failed_substep)
        stats["failed_substep"] = jnp.asarray(failed_substep)
    else:
        stats.pop("substep_root_find_steps")
    n_leaves = treedef.num_leaves
    return Solution(
        ts=joined("ts"),
        ys=jax.tree.unflatten(treedef, [joined(f"y_{i}") for i in range(n_leaves)]),
        energy=joined("energy"),
        constraint=joined("constraint") if "constraint" in chunks[0] else None,
        result=_result(result),
        stats=stats,
    )


def _open_run(directory: pathlib.Path, manifest: dict) -> None:
    """Create `directory` with `manifest`, or check that the run it holds is this one."""
    directory.mkdir(parents=True, exist_ok=True)
    for leftover in directory.glob(".*.tmp"):  # from a write that was interrupted
        leftover.unlink()
    path = directory / _MANIFEST
    if path.exists():
        stored = json.loads(path.read_text())
        differences = [
            f"  {key}: {stored.get(key)!r} there, {value!r} here"
            for key, value in manifest.items()
            if stored.get(key) != value
        ]
        if differences:
            raise ValueError(
                f"{directory} holds a different run (see its {_MANIFEST}):\n"
                + "\n".join(differences)
                + "\nUse another directory, or delete this one to start over."
            )
    elif any(directory.glob("chunk_*.npz")):
        raise ValueError(
            f"{directory} holds chunk files but no {_MANIFEST}, so they cannot be checked "
            "against this run. Use another directory, or delete this one to start over."
        )
    else:
        text = json.dumps(manifest, indent=2) + "\n"
        write_atomically(path, lambda file: file.write(text.encode()))


def write_atomically(path: pathlib.Path, write) -> None:
    """`write(file)` to a temporary file beside `path`, then rename it to `path`: a
    reader (or a rerun after a kill) sees the old file or the complete new one."""
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as file:
            write(file)
            file.flush()
            os.fsync(file.fileno())
        # mkstemp makes the file private (0600); the result gets the permissions of any
        # new file, those the umask leaves of 0666.
        os.chmod(temporary, 0o666 & ~_umask())
        os.replace(temporary, path)
    except BaseException:
        os.unlink(temporary)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


class _Named:
    """A function, shown by its qualified name."""

    def __init__(self, function):
        module = getattr(function, "__module__", None)
        name = getattr(function, "__qualname__", type(function).__qualname__)
        self.name = f"{module}.{name}" if module else name

    def __repr__(self):
        return self.name


def _describe(tree) -> str:
    """The type and fields of a system or method, one line. Functions appear by
    qualified name: their plain repr names no module, and every example calls its
    Hamiltonian `_hamiltonian`."""
    named = jax.tree.map(lambda leaf: _Named(leaf) if callable(leaf) else leaf, tree)
    return eqx.tree_pformat(named, width=1_000_000, short_arrays=False)


def _fingerprint(tree) -> str:
    """A hash of the structure and values of `tree` (`y0` or `args`)."""
    digest = hashlib.sha256(str(jax.tree.structure(tree)).encode())
    for leaf in jax.tree.leaves(tree):
        if eqx.is_array_like(leaf):
            array = np.asarray(leaf)
            digest.update(f"{array.dtype}{array.shape}".encode())
            digest.update(np.ascontiguousarray(array).tobytes())
        else:
            digest.update(repr(leaf).encode())
    return digest.hexdigest()[:16]
