import json
import shutil
import subprocess
import sys
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh
from nhjax._cli import main
from nhjax._chunk_files import describe
from nhjax._runner import run_chunked


GEARBOX = nh.examples.gearbox()
Y0 = GEARBOX.random_initial_state(jax.random.key(0))
# 1000 steps in chunks of 300: three full chunks and a shorter last one.
RUN = dict(dt=0.1, n_steps=1000, save_every=10, chunk_steps=300)


def _chunked(directory, y0=Y0, method=None, **changes):
    settings = {**RUN, **changes}
    return run_chunked(
        GEARBOX.canonical, nh.SIDLA() if method is None else method, y0, settings.pop("dt"),
        settings.pop("n_steps"), directory=directory, progress=False, **settings,
    )


def _bits(solution):
    return [np.asarray(leaf).tobytes() for leaf in jax.tree.leaves((solution.ts, solution.ys, solution.energy, solution.constraint))]


@pytest.fixture(scope="module")
def chunked_run(tmp_path_factory):
    directory = tmp_path_factory.mktemp("gearbox") / "chunks"
    return directory, _chunked(directory)


def test_chunked_run_matches_one_integrate_run_and_writes_every_chunk(chunked_run):
    directory, solution = chunked_run
    whole = nh.integrate(GEARBOX.canonical, nh.SIDLA(), Y0, 0.1, 1000, save_every=10)
    assert solution.ts.shape == whole.ts.shape == (101,)
    np.testing.assert_allclose(solution.ts, whole.ts, rtol=1e-14, atol=0)
    for chunked, unchunked in zip(solution.ys, whole.ys):
        assert chunked.shape == unchunked.shape == (101, 3)
        np.testing.assert_allclose(chunked, unchunked, rtol=0, atol=1e-11)
    np.testing.assert_allclose(solution.energy, whole.energy, rtol=1e-13)
    np.testing.assert_allclose(solution.constraint, whole.constraint, atol=1e-14)
    assert solution.result == nh.RESULTS.successful
    assert int(solution.stats["num_steps"]) == 1000
    assert int(solution.stats["root_find_steps"]) == int(whole.stats["root_find_steps"])

    manifest = json.loads((directory / "manifest.json").read_text())
    assert manifest["method"] == "SIDLA()" and "_gearbox._hamiltonian" in manifest["system"]
    assert (manifest["dt"], manifest["n_steps"], manifest["chunk_steps"], manifest["dtype"]) == (0.1, 1000, 300, "float64")
    files = sorted(path.name for path in directory.glob("chunk_*.npz"))
    assert files == [f"chunk_0000{index}.npz" for index in range(4)]
    saves = []
    for name in files:
        with np.load(directory / name) as chunk:
            assert {"ts", "y_0", "y_1", "energy", "constraint", "result"} <= set(chunk.files)
            saves.append(chunk["ts"])
    # Chunk 0 keeps the initial save, the others start after their first step.
    assert [len(ts) for ts in saves] == [31, 30, 30, 10]
    np.testing.assert_allclose(np.concatenate(saves), solution.ts, rtol=0, atol=0)


def test_resuming_from_the_chunks_left_gives_the_same_bits(chunked_run, tmp_path):
    directory, solution = chunked_run
    copy = tmp_path / "chunks"
    shutil.copytree(directory, copy)
    kept = {path.name: path.stat().st_mtime_ns for path in copy.glob("chunk_0000[01].npz")}
    for lost in ("chunk_00002.npz", "chunk_00003.npz"):
        (copy / lost).unlink()
    (copy / ".chunk_00002.npz.interrupted.tmp").write_bytes(b"half a file")
    resumed = _chunked(copy)
    assert _bits(resumed) == _bits(solution)
    assert {name: (copy / name).stat().st_mtime_ns for name in kept} == kept
    assert (copy / "chunk_00003.npz").exists() and not list(copy.glob("*.tmp"))
    # All chunks on disk: nothing to compute, same result.
    assert _bits(_chunked(copy)) == _bits(solution)


def test_a_directory_holding_another_run_is_refused(chunked_run, tmp_path):
    directory, _ = chunked_run
    with pytest.raises(ValueError, match=r"different run(.|\n)*dt: 0.1 there, 0.05 here"):
        _chunked(directory, dt=0.05)
    with pytest.raises(ValueError, match="initial_state"):
        _chunked(directory, y0=GEARBOX.random_initial_state(jax.random.key(1)))
    with pytest.raises(ValueError, match="method: 'SIDLA\\(\\)' there, 'GonzalezF\\(\\)' here"):
        _chunked(directory, method=nh.GonzalezF())
    with pytest.raises(ValueError, match="chunk_steps: 300 there, 500 here"):
        _chunked(directory, chunk_steps=500)
    stray = tmp_path / "stray"
    stray.mkdir()
    shutil.copy(directory / "chunk_00000.npz", stray)
    with pytest.raises(ValueError, match="no manifest.json"):
        _chunked(stray)
    with pytest.raises(ValueError, match="multiple of save_every=10"):
        _chunked(tmp_path / "new", chunk_steps=25)


def _gearbox_with_pendulum_weight(weight):
    """The gearbox with its pendulum's potential times `weight`: a Hamiltonian of the
    same qualified name whatever the weight, as after editing its body."""

    def hamiltonian(q, p, args):
        return 0.5 * p @ p + 0.5 * (q[0] ** 2 + q[1] ** 2) + weight * (jnp.cos(q[2]) - 0.2 * jnp.sin(2 * q[2]))

    return nh.NonholonomicSystem(hamiltonian, GEARBOX.constraints)


def test_a_system_whose_functions_changed_under_the_same_names_is_refused(tmp_path):
    """A run interrupted after its first chunk, then resumed with the Hamiltonian's body
    edited (same name, same module): refused, naming the computation, not continued
    from chunks of the other system."""
    directory = tmp_path / "chunks"
    settings = dict(dt=0.1, n_steps=40, save_every=10, chunk_steps=20)

    def chunked(system, **changes):
        run = {**settings, **changes}
        return run_chunked(system, nh.SIDLA(), Y0, run.pop("dt"), run.pop("n_steps"), directory=directory, progress=False, **run)

    original, edited = _gearbox_with_pendulum_weight(1.0), _gearbox_with_pendulum_weight(0.5)
    assert describe(original) == describe(edited)
    chunked(original)
    (directory / "chunk_00001.npz").unlink()  # as if interrupted after the first chunk
    with pytest.raises(ValueError, match=r"computation \(what the system's functions compute"):
        chunked(edited)
    # The original system resumes from its own chunk.
    resumed = chunked(original)
    assert resumed.result == nh.RESULTS.successful


def test_killed_simulate_resumes_to_the_bits_of_an_uninterrupted_run(tmp_path):
    arguments = [
        "simulate", "gearbox", "--method", "sidla", "--dt", "0.1", "--t1", "10000",
        "--save-every", "500", "--chunk-steps", "2500", "--no-progress",
    ]
    command = [sys.executable, "-m", "nhjax", *arguments, "--out", str(tmp_path / "killed.npz")]
    chunks = tmp_path / "killed.npz.chunks"
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240
    while not (chunks / "chunk_00000.npz").exists():
        assert process.poll() is None, process.communicate()[1]
        assert time.monotonic() < deadline
        time.sleep(0.005)
    process.kill()
    process.communicate()
    finished = len(list(chunks.glob("chunk_*.npz")))
    assert 1 <= finished < 40 and not (tmp_path / "killed.npz").exists()

    rerun = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert f"resumed: {finished} chunks were on disk" in rerun.stdout
    assert not chunks.exists()

    assert main([*arguments, "--out", str(tmp_path / "whole.npz")]) == 0
    with np.load(tmp_path / "killed.npz") as resumed, np.load(tmp_path / "whole.npz") as whole:
        assert resumed["ts"].shape == (201,) and resumed["q"].shape == (201, 3)
        for name in ("ts", "q", "p", "energy", "constraint"):
            assert resumed[name].tobytes() == whole[name].tobytes(), name


def _breaking_oscillator():
    """x' = (x2, -x1) from x = (1, 0), with an H that is NaN once x1 < -1/2
    (t > 2.09): the step from t = 2 to 2.1 fails there, as a non-finite step."""

    def hamiltonian(x, args):
        return 0.5 * x @ x + 0.0 * jnp.sqrt(x[0] + 0.5)

    def structure(x, args):
        return jnp.array([[0.0, 1.0], [-1.0, 0.0]], x.dtype)

    return nh.SkewGradientSystem(hamiltonian, structure)


def test_a_failed_chunk_stops_the_run_and_says_where(tmp_path):
    system, x0 = _breaking_oscillator(), jnp.array([1.0, 0.0])

    def run(directory, throw, y0=x0):
        return run_chunked(
            system, nh.DiscreteGradient(), y0, 0.1, 60, directory=directory, save_every=2,
            chunk_steps=10, progress=False, throw=throw,
        )

    with pytest.raises(RuntimeError, match=r"Chunk 3 of 6 \(steps 20 to 30, t = 2 to 3\) failed: A step produced a non-finite"):
        run(tmp_path / "raise", throw=True)
    stopped = run(tmp_path / "quiet", throw=False)
    assert stopped.result == nh.RESULTS.nonfinite_step
    assert sorted(path.name for path in (tmp_path / "quiet").glob("chunk_*")) == [f"chunk_0000{i}.npz" for i in range(3)]
    assert stopped.ys.shape == (31, 2)
    assert np.all(np.isfinite(stopped.ys[:11])) and np.all(np.isnan(stopped.ys[11:]))
    np.testing.assert_allclose(stopped.ts[:11], 0.2 * np.arange(11), atol=1e-15)
    # The failed chunk is on disk: a rerun reports it from there.
    with pytest.raises(RuntimeError, match="chunk_00002.npz"):
        run(tmp_path / "quiet", throw=True)

    # In a batch the other trajectory goes on, as under jax.vmap(nh.integrate).
    batch = run(tmp_path / "batch", throw=False, y0=jnp.array([[1.0, 0.0], [0.3, 0.0]]))
    assert batch.ys.shape == (2, 31, 2)
    assert np.asarray(batch.result == nh.RESULTS.nonfinite_step).tolist() == [True, False]
    assert np.asarray(batch.result == nh.RESULTS.successful).tolist() == [False, True]
    np.testing.assert_allclose(batch.ys[1, -1], [0.3 * np.cos(6.0), -0.3 * np.sin(6.0)], atol=1e-2)


def test_a_batch_runs_as_one_vmapped_program_per_chunk(chunked_run, tmp_path):
    others = jax.vmap(GEARBOX.random_initial_state)(jax.random.split(jax.random.key(2), 2))
    states = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), Y0, others)
    batch = _chunked(tmp_path, y0=states, n_steps=600)
    assert batch.ts.shape == (3, 61) and batch.ys[0].shape == (3, 61, 3)
    assert json.loads((tmp_path / "manifest.json").read_text())["batch"] == 3
    assert np.all(np.asarray(batch.stats["num_steps"]) == 600)
    # The first trajectory is the module's single run; the others keep SI-DLA's properties.
    _, single = chunked_run
    for chunked, alone in zip(batch.ys, single.ys):
        np.testing.assert_allclose(chunked[0], alone[:61], rtol=0, atol=1e-11)
    assert np.max(np.abs(batch.constraint)) < 1e-14
    assert np.max(np.abs(batch.energy / batch.energy[:, :1] - 1)) < 1e-2
    with pytest.raises(ValueError, match="must be a 1-D array"):
        run_chunked(GEARBOX.canonical, diffrax.Tsit5(), (states[0][None], states[1][None]), 0.1, 10, directory=tmp_path / "bad")
    with pytest.raises(ValueError, match="progress must be True or False, got 'no'"):
        run_chunked(GEARBOX.canonical, nh.SIDLA(), Y0, 0.1, 10, directory=tmp_path / "bad", progress="no")


def test_a_method_whose_constraint_drifts_continues_across_chunks(tmp_path):
    """GONZALEZ-F's states leave the constraint, so a later chunk starts off it: only the
    first chunk's start is checked, and the chunked run equals one run to roundoff."""
    method = nh.GonzalezF()
    chunked = _chunked(tmp_path / "chunks", method=method)
    assert chunked.result == nh.RESULTS.successful
    whole = nh.integrate(GEARBOX.canonical, method, Y0, RUN["dt"], RUN["n_steps"], save_every=RUN["save_every"])
    assert float(jnp.max(jnp.abs(whole.constraint))) > 1e-6
    for a, b in zip(chunked.ys, whole.ys):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10)
    drifted = jax.tree.map(lambda y: y[-1], whole.ys)
    refused = nh.integrate(GEARBOX.canonical, method, drifted, 0.1, 10, throw=False)
    assert refused.result == nh.RESULTS.constraint_violated_initially
    accepted = nh.integrate(GEARBOX.canonical, method, drifted, 0.1, 10, check_constraint=False)
    assert accepted.result == nh.RESULTS.successful


def test_a_second_writer_of_one_directory_is_refused(tmp_path):
    """Another process holding the directory's lock (here this one, through a second
    open file, as flock locks are per open file): refused, naming the directory, with
    nothing deleted; once released, the run goes ahead."""
    fcntl = pytest.importorskip("fcntl")
    directory = tmp_path / "chunks"
    directory.mkdir()
    leftover = directory / ".chunk_00000.npz.abcd.tmp"  # another writer's file in flight
    leftover.write_bytes(b"partial")
    with open(directory / ".lock", "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(RuntimeError, match=f"Another process is writing chunks in {directory}"):
            _chunked(directory, n_steps=20, chunk_steps=10)
        assert leftover.exists()
        fcntl.flock(held, fcntl.LOCK_UN)
    assert _chunked(directory, n_steps=20, chunk_steps=10).result == nh.RESULTS.successful
