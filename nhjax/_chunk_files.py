"""The files of a chunked run (`nhjax.run_chunked`): the manifest that identifies a
run, one `.npz` file a chunk with what identifies it and a checksum, result codes as
integers, atomic writes, and the chunks joined back into one `nhjax.Solution`."""

import contextlib
import hashlib
import json
import os
import pathlib
import tempfile
import warnings
import zipfile

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._solution import Solution
from ._results import result_codes, RESULTS, SUCCESS


try:
    import fcntl
except ImportError:  # Windows: no locks (`run_lock`)
    fcntl = None


FORMAT = 3
_MANIFEST = "manifest.json"
_CHUNK_PATTERN = "chunk_*.npz"
_SUMMED_STATS = ("num_steps", "root_find_steps", "substep_root_find_steps")


def chunk_path(directory: pathlib.Path, index: int) -> pathlib.Path:
    return directory / f"chunk_{index:05d}.npz"


def run_id(manifest: dict) -> str:
    """A hash of the manifest: what every chunk file of the run records as its run."""
    return hashlib.sha256(json.dumps(manifest, sort_keys=True).encode()).hexdigest()[:16]


# Result codes go to disk as the integer inside the enumeration item, its only leaf.
_RESULT_TREEDEF = jax.tree.structure(RESULTS.successful)


def _code(result) -> np.ndarray:
    return np.asarray(result_codes(result))


def _result(code) -> RESULTS:
    return jax.tree.unflatten(_RESULT_TREEDEF, [jnp.asarray(code)])


def failures(codes) -> str:
    """': message.' for one trajectory; for a batch, which trajectories failed how."""
    codes = np.asarray(codes)
    if codes.ndim == 0:
        return f": {RESULTS[_result(codes)]}"
    lines = [
        f"\n  trajectories {np.flatnonzero(codes == code).tolist()}: {RESULTS[_result(code)]}"
        for code in np.unique(codes[codes != SUCCESS])
    ]
    return "".join(lines) + "\n"


# A forced run's ledger: each chunk's counts from its own start.
_LEDGER = ("work", "dissipated")


def chunk_arrays(solution, *, keep_first, time_axis) -> dict[str, np.ndarray]:
    """A chunk's saves (without the first unless `keep_first`) and stats, as NumPy."""
    saves = dict(ts=solution.ts, energy=solution.energy)
    saves.update({f"y_{i}": leaf for i, leaf in enumerate(jax.tree.leaves(solution.ys))})
    saves.update({name: getattr(solution, name) for name in _LEDGER})
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


def with_identity(chunk: dict[str, np.ndarray], identity: dict) -> dict[str, np.ndarray]:
    """The arrays written for a chunk: its saves and stats, what identifies it, and a
    checksum of all of them."""
    stored = dict(chunk, **{f"chunk_{key}": np.asarray(value) for key, value in identity.items()})
    stored["checksum"] = np.asarray(_checksum(stored))
    return stored


def load_verified(path: pathlib.Path, identity: dict, expected_saves: int, time_axis: int):
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
        elif any(name not in stored for name in ("ts", "energy", *_LEDGER)):
            problem = "lacks saves a chunk holds (written by an older version of nhjax)"
        elif stored["ts"].shape[time_axis] != expected_saves:
            problem = f"does not hold the {expected_saves} saves of this chunk"
    if problem is None:
        return {name: array for name, array in stored.items() if not name.startswith("chunk_")}
    warnings.warn(f"{path} {problem}: not used; computing the chunk again.", RuntimeWarning, stacklevel=3)
    path.unlink()
    return None


def join_chunks(chunks, treedef, n_saved, time_axis) -> Solution:
    def joined(name, parts=None):
        parts = [chunk[name] for chunk in chunks] if parts is None else parts
        array = np.concatenate(parts, axis=time_axis)
        missing = n_saved - array.shape[time_axis]
        if missing:  # a single trajectory that stopped at a failed chunk
            padding = np.full((missing, *array.shape[1:]), np.nan, dtype=array.dtype)
            array = np.concatenate([array, padding])
        return jnp.asarray(array)

    def summed(name):
        """A ledger entry of the whole run: each chunk's, counted from its own start,
        plus what the chunks before it ended with."""
        offset, parts = 0.0, []
        for chunk in chunks:
            parts.append(chunk[name] + offset)
            offset = np.expand_dims(np.take(parts[-1], -1, axis=time_axis), time_axis)
        return joined(name, parts)

    result = chunks[0]["result"]
    for chunk in chunks[1:]:
        result = np.where(result == SUCCESS, chunk["result"], result)
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
        **{name: summed(name) for name in _LEDGER},
    )


# What a manifest entry whose value alone says little stands for.
_MEANINGS = {
    "computation": " (what the system's functions compute: a function's body, or a constant it uses, has changed)",
}


_LOCK = ".lock"


@contextlib.contextmanager
def run_lock(directory: pathlib.Path):
    """Hold an exclusive lock on `directory` (`fcntl.flock` on its `.lock` file) while a
    run writes there; a second process that tries gets a `RuntimeError` naming the
    directory, where it would otherwise delete the first one's temporary files. The
    lock goes with the process (a killed run leaves none behind). Where `fcntl` is
    missing (Windows) nothing is locked."""
    directory.mkdir(parents=True, exist_ok=True)
    if fcntl is None:
        yield
        return
    with open(directory / _LOCK, "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RuntimeError(
                f"Another process is writing chunks in {directory} (it holds {directory / _LOCK}). "
                "Wait for it to finish, or use another directory."
            ) from None
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def open_run(directory: pathlib.Path, manifest: dict) -> None:
    """Create `directory` with `manifest`, or check that the run it holds is this one."""
    directory.mkdir(parents=True, exist_ok=True)
    for leftover in directory.glob(".*.tmp"):  # from a write that was interrupted
        leftover.unlink()
    path = directory / _MANIFEST
    if path.exists():
        stored = json.loads(path.read_text())
        # A key written by only one of the two runs (such as `devices`) differs too.
        keys = [*manifest, *(key for key in stored if key not in manifest)]
        differences = [
            f"  {key}{_MEANINGS.get(key, '')}: {stored.get(key)!r} there, {manifest.get(key)!r} here"
            for key in keys
            if stored.get(key) != manifest.get(key)
        ]
        if differences:
            raise ValueError(
                f"{directory} holds a different run (see its {_MANIFEST}):\n"
                + "\n".join(differences)
                + "\nUse another directory, or delete this one to start over."
            )
    elif any(directory.glob(_CHUNK_PATTERN)):
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


def describe(tree) -> str:
    """The type and fields of a system or method, one line. Functions appear by
    qualified name: their plain repr names no module, and every example calls its
    Hamiltonian `_hamiltonian`."""
    named = jax.tree.map(lambda leaf: _Named(leaf) if callable(leaf) else leaf, tree)
    return eqx.tree_pformat(named, width=1_000_000, short_arrays=False)


def computation_fingerprint(system, y0, args) -> str:
    r"""A hash of what `system` computes: the program (jaxpr, with its constants) of its
    vector field and energy, traced at `y0` (one trajectory's state). Unlike
    `describe`, which names functions, it changes when a function's body does (an edited
    Hamiltonian under the same name, a changed constant it closes over), so that a
    resumed run does not reuse chunks that another system computed."""
    closed = jax.make_jaxpr(lambda y, a: (system.vf(0.0, y, a), system.energy(y, a)))(y0, args)
    digest = hashlib.sha256(str(closed.jaxpr).encode())
    digest.update(fingerprint(list(closed.consts)).encode())
    return digest.hexdigest()[:16]


def fingerprint(tree) -> str:
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
