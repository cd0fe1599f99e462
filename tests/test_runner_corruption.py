"""`run_chunked` never uses a chunk file that is not the one it should be: truncated,
empty, bit-flipped, swapped with another chunk, missing, or another run's. Each is
named in a warning and computed again, and the result is bit-identical to the
uninterrupted run."""

import re
import shutil

import jax
import numpy as np
import pytest

import nhjax as nh
from nhjax._chunk_files import with_identity
from nhjax._runner import run_chunked


GEARBOX = nh.examples.gearbox()
Y0 = GEARBOX.random_initial_state(jax.random.key(0))
OTHER_Y0 = GEARBOX.random_initial_state(jax.random.key(1))
RUN = dict(dt=0.1, n_steps=400, save_every=10, chunk_steps=100)


def _chunked(directory, y0=Y0):
    return run_chunked(
        GEARBOX.canonical, nh.SIDLA(), y0, RUN["dt"], RUN["n_steps"], directory=directory,
        save_every=RUN["save_every"], chunk_steps=RUN["chunk_steps"], progress=False,
    )


def _bits(solution):
    leaves = jax.tree.leaves(
        (solution.ts, solution.ys, solution.energy, solution.constraint, solution.work, solution.dissipated)
    )
    return [np.asarray(leaf).tobytes() for leaf in leaves]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A complete run's chunks, and a complete run's from another initial state."""
    directory = tmp_path_factory.mktemp("run") / "chunks"
    other = tmp_path_factory.mktemp("other") / "chunks"
    return directory, _chunked(directory), other, _chunked(other, OTHER_Y0)


def _truncate(path, _):
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _empty(path, _):
    path.write_bytes(b"")


def _flip_a_bit(path, _):
    """One bit of a stored momentum flipped: zip's CRC catches it when NumPy reads the
    member to its end, the chunk's own checksum otherwise."""
    data = bytearray(path.read_bytes())
    with np.load(path) as chunk:
        stored = chunk["y_1"].tobytes()
    where = data.find(stored) + len(stored) // 2
    data[where] ^= 0x10
    path.write_bytes(bytes(data))


def _rewrite_altered(path, _):
    """A momentum changed and the file rewritten whole (valid zip, old checksum)."""
    with np.load(path) as chunk:
        arrays = {name: chunk[name] for name in chunk.files}
    arrays["y_1"] = arrays["y_1"] + 1e-12
    np.savez(path, **arrays)


def _swap(path, directory):
    shutil.copyfile(directory / "chunk_00002.npz", path)


def _foreign(path, other):
    shutil.copyfile(other / path.name, path)


def _missing(path, _):
    path.unlink()


def _without_ledger(path, _):
    """A chunk as an older version wrote it, without the energy ledger, validly
    checksummed."""
    with np.load(path) as chunk:
        arrays = {name: chunk[name] for name in chunk.files if name not in ("work", "dissipated", "checksum")}
    identity = {key[len("chunk_"):]: arrays.pop(key).item() for key in list(arrays) if key.startswith("chunk_")}
    np.savez(path, **with_identity(arrays, identity))


# name: (what to do to chunk 1, what the warning says)
CORRUPTIONS = {
    "truncated": (_truncate, "cannot be read"),
    "empty": (_empty, "cannot be read"),
    "bit_flipped": (_flip_a_bit, r"cannot be read \(BadZipFile: Bad CRC|does not match its checksum"),
    "altered": (_rewrite_altered, "does not match its checksum"),
    "swapped": (_swap, r"holds chunk 2 \(steps 200 to 300\), not chunk 1 \(steps 100 to 200\)"),
    "foreign": (_foreign, "belongs to another run"),
    "missing": (_missing, None),
    "older": (_without_ledger, "lacks saves a chunk holds"),
}


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_a_bad_chunk_is_named_and_computed_again(runs, tmp_path, name):
    directory, solution, other, _ = runs
    copy = tmp_path / "chunks"
    shutil.copytree(directory, copy)
    damage, message = CORRUPTIONS[name]
    damage(copy / "chunk_00001.npz", other if name == "foreign" else copy)
    if message is None:
        resumed = _chunked(copy)
    else:
        with pytest.warns(RuntimeWarning, match=rf"chunk_00001\.npz ({message}).*computing the chunk again"):
            resumed = _chunked(copy)
    assert resumed.result == nh.RESULTS.successful
    assert _bits(resumed) == _bits(solution)
    # The recomputed chunk is on disk again, and a second resume uses it silently.
    with np.load(copy / "chunk_00001.npz") as chunk:
        assert int(chunk["chunk_index"]) == 1
    assert _bits(_chunked(copy)) == _bits(solution)


def test_a_chunk_that_does_not_start_where_the_previous_ended_is_recomputed(runs, tmp_path):
    """Chunk 1 recomputed from a changed chunk 0 ends elsewhere: chunks 2 and 3, computed
    from the old ends, no longer follow it, and each is named and computed again."""
    directory, solution, _, _ = runs
    copy = tmp_path / "chunks"
    shutil.copytree(directory, copy)
    (copy / "chunk_00001.npz").unlink()
    with np.load(copy / "chunk_00000.npz") as chunk:
        arrays = {name: chunk[name] for name in chunk.files}
    # A different chunk 0, validly written for this run (in the writer's own format):
    # its last momentum moved.
    arrays["y_1"] = arrays["y_1"].copy()
    arrays["y_1"][-1] *= 1 + 1e-9
    identity = {key[len("chunk_"):]: arrays.pop(key).item() for key in list(arrays) if key.startswith("chunk_")}
    arrays.pop("checksum")
    np.savez(copy / "chunk_00000.npz", **with_identity(arrays, identity))
    with pytest.warns(RuntimeWarning, match="starts from another state") as warned:
        resumed = _chunked(copy)
    named = sorted(re.search(r"chunk_(\d+)\.npz starts from another state", str(w.message)).group(1) for w in warned)
    assert named == ["00002", "00003"]
    assert _bits(resumed) != _bits(solution)  # it follows the changed chunk 0
    fresh = np.asarray(resumed.ys[1])
    assert np.all(np.isfinite(fresh))
