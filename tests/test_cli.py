import importlib.metadata
import json
import os
import pathlib
import signal
import subprocess
import sys
import time
import types

import jax
import numpy as np
import pytest

import _nhjax_command
import nhjax as nh
from nhjax._cli import FIGURES, main, METHODS, SYSTEMS


def _run(*arguments):
    return subprocess.run(
        [sys.executable, "-m", "nhjax", *arguments], capture_output=True, text=True, timeout=300
    )


def test_demo_reports_conserved_energy_and_constraints():
    out = _run("demo", "--steps", "400")
    assert out.returncode == 0, out.stderr
    lines = {line.split("  ")[1].strip(): line.split()[-1] for line in out.stdout.splitlines() if "max " in line}
    for name, value in lines.items():
        assert float(value) < 1e-13, (name, value)
    assert len(lines) == 3


def test_bad_arguments_give_a_message_and_nonzero_exit():
    out = _run("demo", "--dt", "-1")
    assert out.returncode != 0 and "--dt must be positive" in out.stderr
    out = _run("fly")
    assert out.returncode != 0 and "invalid choice" in out.stderr


def test_simulate_writes_the_trajectory_with_energy_and_constraint_at_roundoff(tmp_path):
    out = tmp_path / "runs" / "gearbox.npz"
    run = _run(
        "simulate", "gearbox", "--method", "gonzalez-r", "--dt", "0.1", "--t1", "20",
        "--save-every", "10", "--chunk-steps", "100", "--no-progress", "--out", str(out),
    )
    assert run.returncode == 0, run.stderr
    assert out.exists() and not (tmp_path / "runs" / "gearbox.npz.chunks").exists()
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's private 0600
    with np.load(out) as saved:
        assert sorted(saved.files) == ["constraint", "energy", "p", "q", "ts"]
        ts, q, p, energy, constraint = (saved[name] for name in ("ts", "q", "p", "energy", "constraint"))
    assert ts.shape == energy.shape == (21,) and q.shape == p.shape == (21, 3) and constraint.shape == (21, 1)
    np.testing.assert_allclose(ts, np.arange(21.0), atol=1e-12)
    # The saved energy and constraint are those of the saved states, and both are kept.
    gearbox = nh.examples.gearbox()
    np.testing.assert_allclose(energy, 0.5 * np.sum(p**2, axis=1) + jax.vmap(gearbox.potential)(q), rtol=1e-14)
    assert np.max(np.abs(energy / energy[0] - 1)) < 1e-13
    assert np.max(np.abs(p[:, 0] + np.sin(q[:, 2]) * p[:, 1])) < 1e-13
    assert np.ptp(q[:, 0]) > 0.1  # it moved
    summary = {line[:37].strip(): line[37:].strip() for line in run.stdout.splitlines()[1:]}
    assert summary["steps"] == "200"
    assert float(summary["max relative energy error"]) < 1e-13
    assert float(summary["max constraint error |A(q) dH/dp|"]) < 1e-13
    assert summary["result"] == "successful"


def test_simulate_checks_the_output_path_before_any_work(tmp_path, capsys):
    a_file = tmp_path / "afile"
    a_file.write_text("not a directory")
    a_directory = tmp_path / "existing"
    a_directory.mkdir()
    for out, message in [
        (a_file / "x.npz", f"cannot write {a_file / 'x.npz'}: {a_file} is not a directory"),
        (pathlib.Path("/proc/x.npz"), "cannot write /proc/x.npz: "),
        (a_directory, f"{a_directory} is a directory; give the name of the .npz file to write"),
    ]:
        with pytest.raises(SystemExit) as exit:
            main(["simulate", "gearbox", "--method", "sidla", "--dt", "0.1", "--t1", "1", "--out", str(out)])
        assert exit.value.code == 2
        assert f"argument --out: {message}" in capsys.readouterr().err, out
    assert sorted(path.name for path in tmp_path.iterdir()) == ["afile", "existing"]
    assert list(a_directory.iterdir()) == []


def test_a_run_that_blows_up_fails_with_a_message(tmp_path, capsys):
    """Tsit5 at h = 3 on the gearbox overflows: the energy turns inf while the states
    are still finite. That is a failure, not a run with an infinite energy error. (Where
    it overflows depends on roundoff: step 30 or 39 as compiled at two optimisation
    levels; 50 steps reach it at either.)"""
    out = tmp_path / "blown.npz"
    code = main(["simulate", "gearbox", "--method", "tsit5", "--dt", "3", "--t1", "150", "--no-progress", "--out", str(out)])
    assert code == 1
    assert "failed: A step produced a non-finite state, energy or constraint residual" in capsys.readouterr().err
    assert not out.exists()


def test_what_no_run_can_do_is_refused_before_any_work(tmp_path, capsys):
    """A method that composition cannot raise in order, more steps than a run can
    count, and more saves than the disk holds: a message and exit status 2, no
    traceback, nothing written."""
    out = str(tmp_path / "x.npz")
    base = ["simulate", "gearbox", "--t1", "1", "--no-progress", "--out", out]
    with pytest.raises(SystemExit) as exit_status:
        main([*base, "--method", "gonzalez-f", "--order", "4", "--dt", "0.1"])
    assert exit_status.value.code == 2
    assert "argument --order: Composition refuses GonzalezF" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_status:
        main([*base, "--method", "sidla", "--dt", "1e-300"])
    assert exit_status.value.code == 2
    assert "asks for 1e+300 steps, more than the 4.61e+18 a run can count" in capsys.readouterr().err
    assert main([*base, "--method", "sidla", "--dt", "1e-12"]) == 2
    assert "1e+12 saves need about" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("where", ["chunk", "trajectory"])
def test_a_full_disk_is_reported_and_the_chunks_kept(tmp_path, capsys, monkeypatch, where):
    """A write that fails with ENOSPC, of a chunk or of the trajectory after the work:
    exit status 1, a message that says the chunks are kept, and they are."""
    import nhjax._chunk_files
    import nhjax._runner

    original = nhjax._chunk_files.write_atomically
    out = tmp_path / "x.npz"

    def full(path, write):
        if where == "trajectory" and path != out:  # the manifest and chunks go through
            return original(path, write)
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(nhjax._runner if where == "chunk" else nhjax._chunk_files, "write_atomically", full)
    code = main(["simulate", "gearbox", "--method", "sidla", "--dt", "0.1", "--t1", "2", "--no-progress", "--out", str(out)])
    error = capsys.readouterr().err
    assert code == 1 and "No space left on device" in error and "kept" in error
    assert "Traceback" not in error and not out.exists()
    assert (tmp_path / "x.npz.chunks" / "manifest.json").exists()
    assert bool(list((tmp_path / "x.npz.chunks").glob("chunk_*.npz"))) == (where == "trajectory")


_ARGUMENTS = ["simulate", "gearbox", "--method", "gonzalez-r", "--dt", "0.01", "--t1", "100000", "--no-progress"]
# A test run started in the background passes on an ignored SIGINT; a terminal's Ctrl-C
# comes to a process with Python's handler, which the child installs first. The child
# enters through the command's entry point (`_nhjax_command`), as the `nhjax` script does.
_CHILD = "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "


def test_the_command_compiles_with_the_loop_emitter_unless_told_otherwise(monkeypatch, tmp_path):
    """The command adds XLA:CPU's loop emitter to `XLA_FLAGS` (this jaxlib knows it,
    as the suite's own flags show), keeps the other flags, and leaves a user's choice of
    the emitters alone."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert _nhjax_command.xla_knows(_nhjax_command.LOOP_EMITTER)
    assert not _nhjax_command.xla_knows("--xla_no_such_flag_in_any_xla=true")
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=1")
    _nhjax_command.add_xla_flags([_nhjax_command.LOOP_EMITTER])
    assert os.environ["XLA_FLAGS"].split() == ["--xla_backend_optimization_level=1", _nhjax_command.LOOP_EMITTER]
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    _nhjax_command.add_xla_flags([_nhjax_command.LOOP_EMITTER])
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=true"
    monkeypatch.delenv("XLA_FLAGS")
    _nhjax_command.add_xla_flags([_nhjax_command.LOOP_EMITTER])
    assert os.environ["XLA_FLAGS"] == _nhjax_command.LOOP_EMITTER


_LOOP_PROGRAM = """
import jax, jax.numpy as jnp
loop = lambda x: jax.lax.fori_loop(0, 10, lambda i, y: jnp.sin(y) @ jnp.ones((64, 64)), x)
print(jax.jit(loop).lower(jnp.ones(64)).compile().as_text())
"""


def test_the_command_compiles_whole_loops_into_one_function(monkeypatch, tmp_path):
    """The command's `WHOLE_LOOPS` flag (added unless `XLA_FLAGS` sets XLA's backend
    options) makes XLA:CPU compile a loop whose arrays pass its default size limit (a
    64 x 64 matrix, 16 KiB) into one function, which it otherwise runs operation by
    operation."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert _nhjax_command.xla_knows(_nhjax_command.WHOLE_LOOPS)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    _nhjax_command.add_xla_flags([_nhjax_command.LOOP_EMITTER, _nhjax_command.WHOLE_LOOPS])
    assert os.environ["XLA_FLAGS"].split() == [_nhjax_command.LOOP_EMITTER, _nhjax_command.WHOLE_LOOPS]
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0")
    _nhjax_command.add_xla_flags([_nhjax_command.WHOLE_LOOPS])
    assert os.environ["XLA_FLAGS"] == "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0"
    hoisted = []
    for flags in ("", _nhjax_command.WHOLE_LOOPS):
        environment = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
        program = subprocess.run(
            [sys.executable, "-c", _LOOP_PROGRAM], env=environment, capture_output=True, text=True, check=True
        ).stdout
        hoisted.append('xla_cpu_small_call="true"' in program)
    assert hoisted == [False, True]


def test_the_command_asks_for_one_cpu_device_per_usable_core(monkeypatch, tmp_path):
    """As many XLA:CPU devices as the cores this process may use, none asked for on one
    core or where `JAX_NUM_CPU_DEVICES` sets the count; a count in `XLA_FLAGS` stays
    the user's; and XLA gives a fresh process the devices asked for."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("JAX_NUM_CPU_DEVICES", raising=False)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 2, 5}, raising=False)
    assert _nhjax_command.one_device_per_core() == ["--xla_force_host_platform_device_count=3"]
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {4}, raising=False)
    assert _nhjax_command.one_device_per_core() == []
    monkeypatch.setenv("JAX_NUM_CPU_DEVICES", "2")
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert _nhjax_command.one_device_per_core() == []
    monkeypatch.delenv("JAX_NUM_CPU_DEVICES")
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
    _nhjax_command.add_xla_flags(_nhjax_command.one_device_per_core())
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=1"
    monkeypatch.delenv("XLA_FLAGS")
    _nhjax_command.add_xla_flags(_nhjax_command.one_device_per_core())
    environment = dict(os.environ, JAX_PLATFORMS="cpu")
    devices = subprocess.run(
        [sys.executable, "-c", "import jax; print(len(jax.devices()))"],
        env=environment, capture_output=True, text=True, check=True,
    ).stdout
    assert int(devices) == 2


def test_the_command_keeps_its_compiled_programs_for_its_next_run(monkeypatch, tmp_path):
    """The command points JAX's persistent compilation cache at the user's cache folder,
    bounded, unless `JAX_COMPILATION_CACHE_DIR` names one (kept); a run writes its
    programs there and a rerun reads them back: the same trajectory, bitwise, and
    nothing new in the cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "users"))
    _nhjax_command.use_compilation_cache()
    assert os.environ["JAX_COMPILATION_CACHE_DIR"] == str(tmp_path / "users")
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR")
    monkeypatch.delenv("JAX_COMPILATION_CACHE_MAX_SIZE", raising=False)
    _nhjax_command.use_compilation_cache()
    cache = tmp_path / "nhjax" / "compilation"
    assert os.environ["JAX_COMPILATION_CACHE_DIR"] == str(cache) and cache.is_dir()
    assert os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"] == str(2**30)
    # The suite's setting, explicit: every program is cached, however fast it compiled.
    monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR")
    command = "import sys, _nhjax_command; sys.exit(_nhjax_command.main(sys.argv[1:]))"
    entries, trajectories = [], []
    for run in range(2):
        out = tmp_path / f"run{run}.npz"
        arguments = ["simulate", "sleigh", "--method", "sidla", "--dt", "0.1", "--t1", "2", "--no-progress"]
        finished = subprocess.run(
            [sys.executable, "-c", command, *arguments, "--out", str(out)], capture_output=True, text=True, timeout=300
        )
        assert finished.returncode == 0, finished.stderr
        entries.append(sorted(path.name for path in cache.glob("*-cache")))
        trajectories.append(dict(np.load(out)))
    assert entries[0] and entries[1] == entries[0]
    for name, values in trajectories[0].items():
        np.testing.assert_array_equal(trajectories[1][name], values)


def test_the_flag_probe_is_asked_once_per_jaxlib_version(monkeypatch, tmp_path):
    """`xla_knows` remembers each answer for this jaxlib in the user's cache, and asks a
    child process again where the cache is unreadable."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    children = []
    run = subprocess.run

    def counted(*arguments, **options):
        children.append(arguments)
        return run(*arguments, **options)

    monkeypatch.setattr(_nhjax_command.subprocess, "run", counted)
    unknown = "--xla_no_such_flag_in_any_xla=true"
    for _ in range(2):
        assert _nhjax_command.xla_knows(_nhjax_command.LOOP_EMITTER)
        assert not _nhjax_command.xla_knows(unknown)
    assert len(children) == 2
    cache = _nhjax_command.flag_cache()
    assert cache.parent.parent == tmp_path
    saved = json.loads(cache.read_text())
    version = importlib.metadata.version("jaxlib")
    assert saved == {f"jaxlib {version} {_nhjax_command.LOOP_EMITTER}": True, f"jaxlib {version} {unknown}": False}
    cache.write_text("{not json")
    assert _nhjax_command.xla_knows(_nhjax_command.LOOP_EMITTER)
    assert len(children) == 3


def test_an_interrupt_ends_the_command_cleanly(tmp_path):
    """Ctrl-C during the compilation or the run: the exit status of SIGINT (130) and one
    line, not a crash."""
    command = _CHILD + "import _nhjax_command; sys.exit(_nhjax_command.main(sys.argv[1:]))"
    process = subprocess.Popen(
        [sys.executable, "-c", command, *_ARGUMENTS, "--out", str(tmp_path / "x.npz")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    time.sleep(6)
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, stderr
    assert stderr.strip().endswith("nhjax: interrupted")


def test_an_interrupt_while_the_package_imports_ends_the_command_cleanly(tmp_path):
    """Ctrl-C while `nhjax` is still importing JAX (seconds on a loaded machine): the
    signal is sent from inside the import of jax itself, whatever the machine's speed,
    and the command still leaves with 130 and one line, no traceback."""
    command = _CHILD + (
        "import builtins, os, _nhjax_command\n"
        "real = builtins.__import__\n"
        "def interrupting(name, *args, **kwargs):\n"
        "    if name == 'jax':\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "    return real(name, *args, **kwargs)\n"
        "builtins.__import__ = interrupting\n"
        "sys.exit(_nhjax_command.main(sys.argv[1:]))\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", command, *_ARGUMENTS, "--out", str(tmp_path / "x.npz")],
        capture_output=True, text=True, timeout=120,
    )
    assert run.returncode == 130, run.stderr
    assert run.stderr.strip() == "nhjax: interrupted"


def test_simulate_help_names_every_option_system_and_method():
    out = _run("simulate", "--help")
    assert out.returncode == 0
    for name in ("--method", "--dt", "--t1", "--save-every", "--out", "--chunk-steps", "--seed", "--start", "--no-progress"):
        assert name in out.stdout, name
    for name in (*SYSTEMS, *METHODS):
        assert f"\n  {name}" in out.stdout, name
    # A name longer than its column stands on its own line, not glued to its text.
    assert "\n  dopri8-projection\n" in out.stdout and "\n  MODULE:FACTORY\n" in out.stdout
    # --order names each scheme and its substeps (Suzuki's 5, Kahan & Li's 9 and 17).
    text = " ".join(out.stdout.split())
    for described in ("4 (suzuki-4, 5 substeps a step)", "6 (kahan-li-6, 9 substeps", "8 (kahan-li-8, 17 substeps"):
        assert described in text, described


def test_simulate_composes_to_higher_order(tmp_path):
    """--order 4 on the disk: Suzuki's composition of GONZALEZ-R, energy and constraint
    still at roundoff, and the final state closer to the exact flow than at order 2."""
    finals = {}
    for order in ("2", "4"):
        out = tmp_path / f"disk-{order}.npz"
        run = _run(
            "simulate", "disk", "--method", "gonzalez-r", "--order", order, "--dt", "0.25", "--t1", "5",
            "--start", "rho1=1.3", "--start", "rho2=0.9", "--no-progress", "--out", str(out),
        )
        assert run.returncode == 0, run.stderr
        with np.load(out) as saved:
            finals[order] = saved["q"][-1]
            assert np.max(np.abs(saved["energy"] / saved["energy"][0] - 1)) < 1e-13
    assert "GONZALEZ-R composed to order 4" in run.stdout
    disk = nh.examples.rolling_disk()
    exact = disk.from_adapted(disk.exact_solution(5.0, disk.initial_state(rho1=1.3, rho2=0.9)))[0]
    assert np.max(np.abs(finals["4"] - exact)) < np.max(np.abs(finals["2"] - exact)) / 20
    refused = _run("simulate", "disk", "--method", "tsit5", "--order", "4", "--dt", "0.25", "--t1", "5")
    assert refused.returncode == 2 and "not symmetric" in refused.stderr


def test_simulate_with_the_projected_dopri8(tmp_path, capsys):
    """dopri8-projection on the disk: energy and constraint at roundoff, the final state
    at Dopri8's accuracy; it does not compose."""
    out = tmp_path / "disk.npz"
    code = main(["simulate", "disk", "--method", "dopri8-projection", "--dt", "0.25", "--t1", "5",
                 "--start", "rho1=1.3", "--start", "rho2=0.9", "--no-progress", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    disk = nh.examples.rolling_disk()
    exact = disk.from_adapted(disk.exact_solution(5.0, disk.initial_state(rho1=1.3, rho2=0.9)))[0]
    with np.load(out) as saved:
        assert np.max(np.abs(saved["energy"] / saved["energy"][0] - 1)) < 1e-14
        assert np.max(np.abs(saved["constraint"])) < 1e-14
        assert np.max(np.abs(saved["q"][-1] - exact)) < 1e-8
    with pytest.raises(SystemExit) as exit:
        main(["simulate", "disk", "--method", "dopri8-projection", "--order", "4", "--dt", "0.25", "--t1", "5"])
    assert exit.value.code == 2 and "not symmetric" in capsys.readouterr().err


def test_every_example_runs_from_the_command_line(tmp_path, capsys):
    """Each example of the catalogue, from its usual start, with SI-DLA in canonical
    coordinates where it has them and GONZALEZ on its reduced equations otherwise: the
    trajectory written in that form, the energy of the saved states the example's own."""
    for name, example in nh.examples.EXAMPLES.items():
        example = example()
        method, form = ("sidla", "canonical") if "canonical" in example.forms() else ("gonzalez", "adapted")
        out = tmp_path / f"{name}.npz"
        code = main(["simulate", name, "--method", method, "--dt", "0.1", "--t1", "0.3", "--no-progress", "--out", str(out)])
        assert code == 0, capsys.readouterr().err
        assert f"{name}" in capsys.readouterr().out
        with np.load(out) as saved:
            states = (saved["q"], saved["p"]) if form == "canonical" else saved["x"]
            energy = saved["energy"]
        start = jax.tree.map(lambda y: y[0], states)
        np.testing.assert_allclose(start, example.start(form), rtol=0, atol=1e-15)
        np.testing.assert_allclose(energy[0], example.system(form).energy(start, example.args), rtol=1e-14)
        assert energy.shape == (4,) and np.all(np.isfinite(energy))


def test_a_method_needs_the_form_it_integrates(tmp_path, capsys):
    base = ["--dt", "0.1", "--t1", "1", "--out", str(tmp_path / "x.npz")]
    with pytest.raises(SystemExit) as exit:
        main(["simulate", "suslov", "--method", "gonzalez-r", *base])
    assert exit.value.code == 2
    assert "gonzalez-r integrates the canonical form, and the suslov example comes in adapted form only" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit:
        main(["simulate", "gearbox", "--method", "avf", *base])
    assert exit.value.code == 2
    assert "avf integrates the adapted form, and the gearbox example comes in canonical, lagrangian" in capsys.readouterr().err


def test_a_method_of_either_form_takes_the_one_the_example_has(tmp_path, capsys):
    """The energy-preserving collocation integrates Suslov's reduced equations (it has
    no canonical form) and the gearbox in canonical coordinates."""
    for name, saved_as in (("suslov", ("x",)), ("gearbox", ("q", "p"))):
        out = tmp_path / f"{name}.npz"
        arguments = ["simulate", name, "--method", "ep-collocation-4", "--dt", "0.2", "--t1", "2", "--no-progress"]
        assert main([*arguments, "--out", str(out)]) == 0, capsys.readouterr().err
        printed = capsys.readouterr().out
        relative_error = float(printed.split("max relative energy error")[1].split()[0])
        assert relative_error < 1e-13, printed
        with np.load(out) as saved:
            assert all(key in saved for key in saved_as) and saved["energy"].shape == (11,)


def test_unknown_system_or_method_lists_the_valid_ones():
    out = _run("simulate", "bicycle", "--method", "sidla", "--dt", "0.1", "--t1", "1")
    assert out.returncode != 0 and "invalid choice: 'bicycle'" in out.stderr
    assert all(f"'{name}'" in out.stderr for name in SYSTEMS)
    out = _run("simulate", "sleigh", "--method", "rk4", "--dt", "0.1", "--t1", "1")
    assert out.returncode != 0 and "invalid choice: 'rk4'" in out.stderr
    assert all(f"'{name}'" in out.stderr for name in METHODS)


def test_bad_simulate_numbers_give_a_message_and_nonzero_exit(capsys):
    out = _run("simulate", "sleigh", "--method", "sidla", "--dt", "0", "--t1", "1")
    assert out.returncode != 0 and "--dt must be positive and finite, got 0.0" in out.stderr
    for arguments, message in [
        (["--dt", "-0.1", "--t1", "1"], "--dt must be positive"),
        (["--dt", "nan", "--t1", "1"], "--dt must be positive and finite, got nan"),
        (["--dt", "0.1", "--t1", "-1"], "--t1 must be positive"),
        (["--dt", "0.1", "--t1", "inf"], "--t1 must be positive and finite, got inf"),
        (["--dt", "0.3", "--t1", "1"], "whole number of steps: t1/h = 3.33333"),
        (["--dt", "0.1", "--t1", "1", "--save-every", "3"], "divisor of the number of steps t1/h = 10, got 3"),
        (["--dt", "0.1", "--t1", "1", "--save-every", "2", "--chunk-steps", "5"], "multiple of --save-every 2, got 5"),
        (["--dt", "0.1", "--t1", "1", "--seed", "3"], "--seed needs a system with random initial states"),
        (["--dt", "0.1", "--t1", "1", "--start", "angle=0.2"], "initial state takes x1, x2, theta, rho1, rho2, not 'angle'"),
        (["--dt", "0.1", "--t1", "1", "--start", "rho1"], "expected NAME=VALUE with a number VALUE, got 'rho1'"),
        (["--dt", "0.1", "--t1", "1", "--start", "rho1=0.1", "--seed", "1"], "--seed needs a system with random"),
        (["--dt", "0.1", "--t1", "1", "--order", "3"], "invalid choice: 3"),
    ]:
        with pytest.raises(SystemExit) as exit:
            main(["simulate", "sleigh", "--method", "sidla", *arguments])
        assert exit.value.code != 0
        assert message in capsys.readouterr().err, arguments


def test_reproduce_passes_its_options_on(monkeypatch, tmp_path, capsys):
    calls = []

    def reproduce(figures, *, quick, out, progress=True):
        calls.append((figures, quick, out, progress))
        return {"fig2": {"agrees": True, "verdict": "rho settles at (0, 0.6)"}, "wall_time_s": 1.0}

    monkeypatch.setitem(sys.modules, "nhjax._reproduce", types.SimpleNamespace(reproduce=reproduce))
    assert main(["reproduce", "fig2", "fig1", "--quick", "--out", str(tmp_path), "--no-progress"]) == 0
    assert "fig2: agrees with the paper: rho settles at (0, 0.6)" in capsys.readouterr().out
    assert main(["reproduce"]) == 0
    assert calls == [
        (("fig2", "fig1"), True, tmp_path, False),
        (FIGURES, False, pathlib.Path("nhjax-reproduction"), True),
    ]
    with pytest.raises(SystemExit) as exit:
        main(["reproduce", "fig6"])
    assert exit.value.code != 0 and "invalid choice: 'fig6'" in capsys.readouterr().err


def test_reproduce_help_names_its_options():
    out = _run("reproduce", "--help")
    assert out.returncode == 0
    assert all(name in out.stdout for name in ("--quick", "--out", "fig1", "fig4", "all"))


def test_reproduce_quick_end_to_end_through_the_command(tmp_path, capsys):
    """`nhjax reproduce fig2 --quick` for real (the cheapest figure; all four figures at
    reduced sizes are checked in tests/test_reproduce.py): the files, the parsed
    results, and the sleigh settling as Proposition 4.1 says."""
    import json

    assert main(["reproduce", "fig2", "--quick", "--out", str(tmp_path), "--no-progress"]) == 0
    assert (tmp_path / "fig2.png").stat().st_size > 0
    assert "fig2.png" in (tmp_path / "report.md").read_text()
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["fig2"]["agrees"] is True
    assert "agrees" in capsys.readouterr().out
