"""`nhjax simulate --system MODULE:FACTORY`: a user's own system from the command line,
with the methods, --order, chunked runs that resume, the summary line, and errors that
name what is wrong with the factory."""

import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest


# A particle in a harmonic potential under the nonholonomic constraint dz = y dx
# (Bloch's nonholonomic particle): M = I, so dH/dp = p and the constraint is
# p_z - y p_x = 0.
USER_MODULE = textwrap.dedent(
    """
    import jax.numpy as jnp

    import nhjax as nh


    def hamiltonian(q, p, args):
        return 0.5 * p @ p + 0.5 * args["stiffness"] * q @ q


    def constraints(q, args):
        one = jnp.ones_like(q[0])
        return jnp.stack([-q[1], 0.0 * one, one])[None, :]


    def factory():
        system = nh.NonholonomicSystem(hamiltonian, constraints)
        args = {"stiffness": 1.5}
        q0 = jnp.array([0.3, -0.2, 0.1])
        p0 = system.project_momentum(q0, jnp.array([0.5, 0.4, -0.3]), args)
        return system, (q0, p0), args


    def driven():
        # The particle with viscous friction and a periodic push along x.
        _, y0, args = factory()
        system = nh.NonholonomicSystem(
            hamiltonian,
            constraints,
            dissipation=lambda q, p, args: 0.1 * jnp.eye(3, dtype=q.dtype),
            force=lambda t, q, p, args: jnp.stack([jnp.cos(t), 0.0 * t, 0.0 * t]),
        )
        return system, y0, args


    def not_a_tuple():
        return factory()[0]


    def wrong_system():
        return "system", factory()[1], None


    def wrong_state():
        system, (q0, p0), args = factory()
        return system, (q0, p0[:2]), args


    def raises():
        raise RuntimeError("no such part")


    def needs_an_argument(stiffness):
        return factory()


    def exits():
        raise SystemExit(0)
    """
)


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "particle.py").write_text(USER_MODULE)
    return tmp_path


def _simulate(folder, *arguments, **options):
    return subprocess.run(
        [sys.executable, "-m", "nhjax", "simulate", *arguments, "--no-progress"],
        capture_output=True, text=True, timeout=600, cwd=folder, **options,
    )


def _saved(path):
    with np.load(path) as saved:
        return {name: saved[name] for name in saved.files}


@pytest.mark.parametrize("method, order", [("gonzalez-r", "2"), ("gonzalez-r", "4"), ("sidla", "2")])
def test_a_users_system_runs_with_the_methods_and_keeps_what_they_keep(folder, method, order):
    run = _simulate(
        folder, "--system", "particle:factory", "--method", method, "--order", order,
        "--dt", "0.1", "--t1", "20", "--save-every", "10",
    )
    assert run.returncode == 0, run.stderr
    assert "particle:factory()" in run.stdout and "max relative energy error" in run.stdout
    suffix = "" if order == "2" else f"-order{order}"
    saved = _saved(folder / f"particle.factory-{method}{suffix}.npz")
    q, p, energy = saved["q"], saved["p"], saved["energy"]
    assert q.shape == p.shape == (21, 3)
    # Energy and constraint recomputed from the saved states, by hand.
    np.testing.assert_allclose(energy, 0.5 * np.sum(p**2, axis=1) + 0.75 * np.sum(q**2, axis=1), rtol=1e-14)
    assert np.max(np.abs(p[:, 2] - q[:, 1] * p[:, 0])) < 1e-13
    if method == "gonzalez-r":
        assert np.max(np.abs(energy / energy[0] - 1)) < 1e-13
    else:
        assert 1e-10 < np.max(np.abs(energy / energy[0] - 1)) < 1e-2
    assert np.ptp(q[:, 0]) > 0.1


def test_a_users_forced_system_reports_its_energy_balance(folder):
    """A factory whose system has a force and a dissipation: the run saves the work and
    the dissipated energy, the summary prints the balance, and the balance holds in the
    saved arrays to roundoff."""
    run = _simulate(
        folder, "--system", "particle:driven", "--method", "gonzalez-r", "--dt", "0.1", "--t1", "20", "--out", "driven.npz"
    )
    assert run.returncode == 0, run.stderr
    assert "max relative energy balance error" in run.stdout and "energy supplied, dissipated" in run.stdout
    saved = _saved(folder / "driven.npz")
    energy, work, dissipated = saved["energy"], saved["work"], saved["dissipated"]
    assert np.max(np.abs(energy - energy[0] - (work - dissipated))) < 1e-13 * np.max(np.abs(energy))
    assert np.all(np.diff(dissipated) > 0) and np.ptp(work) > 0.1


def test_the_positional_form_is_the_same_run(folder):
    for arguments, out in [(("particle:factory",), "a.npz"), (("--system", "particle:factory"), "b.npz")]:
        run = _simulate(folder, *arguments, "--method", "idla", "--dt", "0.1", "--t1", "5", "--out", out)
        assert run.returncode == 0, run.stderr
    a, b = _saved(folder / "a.npz"), _saved(folder / "b.npz")
    assert all(np.array_equal(a[name], b[name]) for name in a)


def test_an_interrupted_run_resumes_from_its_chunks(folder):
    """Interrupted after its first chunks, the rerun continues from them and writes
    the same trajectory as a run never interrupted (chunked runs are bit-for-bit
    reproducible)."""
    arguments = ["--system", "particle:factory", "--method", "sidla", "--dt", "0.01", "--t1", "400",
                 "--save-every", "100", "--chunk-steps", "500"]
    command = (
        "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "from nhjax._cli import main; sys.exit(main(sys.argv[1:]))"
    )
    process = subprocess.Popen(
        [sys.executable, "-c", command, "simulate", *arguments, "--no-progress", "--out", "run.npz"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=folder,
    )
    chunks = folder / "run.npz.chunks"
    deadline = time.monotonic() + 300
    while len(list(chunks.glob("chunk_*.npz"))) < 2 and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, stderr
    on_disk = len(list(chunks.glob("chunk_*.npz")))
    assert 2 <= on_disk < 80
    resumed = _simulate(folder, *arguments, "--out", "run.npz")
    assert resumed.returncode == 0, resumed.stderr
    assert f"(resumed: {on_disk} chunks were on disk)" in resumed.stdout
    whole = _simulate(folder, *arguments, "--out", "whole.npz")
    assert whole.returncode == 0, whole.stderr
    a, b = _saved(folder / "run.npz"), _saved(folder / "whole.npz")
    assert all(np.array_equal(a[name], b[name]) for name in a)


@pytest.mark.parametrize(
    "system, message",
    [
        ("missing_module:factory", "cannot import module 'missing_module' of missing_module:factory: ModuleNotFoundError"),
        ("particle:absent", "module 'particle' has no function 'absent'"),
        ("particle:not_a_tuple", "must return (system, (q0, p0), args), the system a NonholonomicSystem; it returned NonholonomicSystem"),
        ("particle:wrong_system", "its system is a str"),
        ("particle:wrong_state", "returned an initial state that does not fit its system"),
        ("particle:raises", "particle:raises() failed (it is called with no arguments): RuntimeError: no such part"),
        ("particle:needs_an_argument", "particle:needs_an_argument() failed (it is called with no arguments): TypeError"),
        ("particle:exits", "particle:exits() failed (it is called with no arguments): SystemExit: 0"),
    ],
)
def test_a_factory_that_cannot_be_used_is_named_with_its_problem(folder, system, message):
    run = _simulate(folder, "--system", system, "--method", "sidla", "--dt", "0.1", "--t1", "1")
    assert run.returncode == 2
    assert message in run.stderr, run.stderr
    assert "Traceback" not in run.stderr


def test_the_system_is_given_once(folder):
    both = _simulate(folder, "gearbox", "--system", "particle:factory", "--method", "sidla", "--dt", "0.1", "--t1", "1")
    neither = _simulate(folder, "--method", "sidla", "--dt", "0.1", "--t1", "1")
    malformed = _simulate(folder, "--system", "particle", "--method", "sidla", "--dt", "0.1", "--t1", "1")
    for run in (both, neither):
        assert run.returncode == 2 and "give the system once" in run.stderr
    assert malformed.returncode == 2 and "expected MODULE:FACTORY, got 'particle'" in malformed.stderr
