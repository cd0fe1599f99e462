"""The time loop: saving, statistics, jit/vmap, compile-once, and bad input."""

import pathlib

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh

from .helpers import final_state_errors


QUARTIC = nh.examples.chaotic_quartic()
METHOD = nh.DiscreteGradient()


def test_vmapped_batch_of_200_equals_single_runs():
    states = QUARTIC.random_initial_states(jax.random.key(1), 200)
    run = lambda x0: nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 50, save_every=10)  # noqa: E731
    batch = jax.vmap(run)(states)
    assert batch.ys.shape == (200, 6, 13)
    singles = np.stack([np.asarray(run(x0).ys) for x0 in states])
    np.testing.assert_allclose(batch.ys, singles, rtol=1e-13, atol=1e-13)
    assert bool(jnp.all(batch.result == nh.RESULTS.successful))


def test_compiles_once_for_new_states_step_sizes_and_parameters():
    traces = []

    def hamiltonian(x, args):
        traces.append(None)
        return 0.5 * args["k"] * x @ x

    system = nh.SkewGradientSystem(hamiltonian, lambda x, args: jnp.array([[0.0, 1.0], [-1.0, 0.0]]))
    nh.integrate(system, METHOD, jnp.array([1.0, 0.0]), 0.1, 20, args={"k": 1.0})
    count = len(traces)
    nh.integrate(system, METHOD, jnp.array([0.3, 0.5]), 0.05, 20, args={"k": 2.0})
    nh.integrate(system, METHOD, jnp.array([0.2, 0.1]), jnp.array(0.2), 20, args={"k": 3.0})
    assert len(traces) == count


def test_save_every_and_times():
    x0 = QUARTIC.initial_state(0.5)
    every = nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 40)
    sparse = nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 40, save_every=8)
    np.testing.assert_allclose(sparse.ts, 0.8 * jnp.arange(6), rtol=1e-15)
    # Two programs compiled apart (at the suite's optimisation level they may fuse,
    # and round, differently).
    np.testing.assert_allclose(sparse.ys, every.ys[::8], rtol=1e-14, atol=1e-14)
    later = nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 40, save_every=8, t0=1.0)
    np.testing.assert_allclose(later.ts, 1.0 + 0.8 * jnp.arange(6), rtol=1e-15)
    np.testing.assert_allclose(later.ys, sparse.ys, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(sparse.energy, every.energy[::8], rtol=1e-14)
    assert sparse.constraint is None
    # Every step ends exactly at t0 + k dt, rounded as that expression is.
    later_every = nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 40, t0=1.0)
    np.testing.assert_array_equal(later_every.ts, 1.0 + jnp.float64(0.1) * jnp.arange(41, dtype=jnp.float64))
    assert int(later_every.stats["num_steps"]) == 40
    assert int(every.stats["num_steps"]) == 40
    assert int(every.stats["root_find_steps"]) >= 40 and int(every.stats["max_root_find_steps"]) >= 1


def test_a_step_count_traced_up_to_a_bound_compiles_once_and_saves_what_the_static_runs_do():
    """An order study's sweep to t = 4: `n_steps` traced up to `max_steps`, one
    compiled program; save i is the static run's state after min(8 i, n) steps, at
    its time, so that the last save is the final state (n = 13: a final step that
    save_every does not divide)."""
    x0 = QUARTIC.initial_state(0.5)
    bounded = jax.jit(
        lambda dt, n: nh.integrate(QUARTIC.adapted, METHOD, x0, dt, n, save_every=8, max_steps=40)
    )
    for dt, n in ((0.1, 40), (0.2, 20), (0.4, 10), (4 / 13, 13)):
        solution = bounded(dt, n)
        static = nh.integrate(QUARTIC.adapted, METHOD, x0, dt, n)
        steps = np.minimum(8 * np.arange(6), n)
        np.testing.assert_array_equal(solution.ts, static.ts[steps])
        np.testing.assert_allclose(solution.ys, static.ys[steps], rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(solution.energy, static.energy[steps], rtol=1e-14)
        assert int(solution.stats["num_steps"]) == n
    assert bounded._cache_size() == 1
    batch = jax.vmap(bounded)(jnp.array([0.2, 0.4]), jnp.array([20, 10]))
    np.testing.assert_allclose(batch.ys[:, -1], [bounded(0.2, 20).ys[-1], bounded(0.4, 10).ys[-1]], rtol=1e-13)
    np.testing.assert_array_equal(batch.stats["num_steps"], [20, 10])


def test_concrete_arrays_closed_over_by_a_jitted_function_are_checked_as_concrete():
    """A step size, step count and tolerances held as concrete arrays and closed over by
    `jax.jit`: their checks compare Python floats (a comparison of the arrays would be
    traced there) and still refuse bad values at once."""
    x0, dt, n = QUARTIC.initial_state(0.5), jnp.asarray(0.1), jnp.asarray(20)
    run = jax.jit(lambda x: nh.integrate(QUARTIC.adapted, METHOD, x, dt, n, max_steps=20).ys[-1])
    np.testing.assert_allclose(run(x0), nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 20).ys[-1], rtol=1e-13)
    negative = jnp.asarray(-0.1)
    with pytest.raises(ValueError, match="dt must be positive"):
        jax.jit(lambda x: nh.integrate(QUARTIC.adapted, METHOD, x, negative, 20).ys)(x0)
    y0, tolerance, negative = GEARBOX.random_initial_state(jax.random.key(0)), jnp.asarray(1e-8), jnp.asarray(-1e-8)
    adaptive = jax.jit(lambda y: nh.integrate_adaptive(GEARBOX.canonical, y, jnp.asarray(1.0), rtol=tolerance, atol=tolerance).ys)
    assert bool(jnp.all(jnp.isfinite(adaptive(y0)[0])))
    with pytest.raises(ValueError, match="rtol and atol must be positive"):
        jax.jit(lambda y: nh.integrate_adaptive(GEARBOX.canonical, y, 1.0, rtol=negative).ys)(y0)


def test_step_counts_outside_the_bound():
    x0 = QUARTIC.initial_state(0.5)
    with pytest.raises(ValueError, match=r"n_steps must lie in \[1, max_steps\] = \[1, 40\], got 41"):
        nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 41, max_steps=40)
    with pytest.raises(ValueError, match="save_every=3 must divide max_steps=40"):
        nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 12, save_every=3, max_steps=40)
    with pytest.raises(ValueError, match="n_steps must be an integer scalar"):
        nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, jnp.array(10.0), max_steps=40)
    # Without the bound, a traced count is named with what it needs.
    with pytest.raises(ValueError, match="a traced number of steps needs max_steps, a static bound on it"):
        jax.jit(lambda n: nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, n).ys)(10)
    # A string was taken for True.
    with pytest.raises(ValueError, match="check_constraint must be True, False or a boolean scalar, got 'no'"):
        nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 10, check_constraint="no")
    with pytest.raises(ValueError, match="check_constraint must be True, False or a boolean scalar"):
        nh.integrate_ensemble(QUARTIC.adapted, METHOD, x0[None], 0.1, 10, check_constraint=1)
    for name in ("throw", "progress"):
        with pytest.raises(ValueError, match=f"{name} must be True or False, got 'False'"):
            nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 10, **{name: "False"})
    with pytest.raises(ValueError, match="throw must be True or False"):
        nh.integrate_ensemble(QUARTIC.adapted, METHOD, x0[None], 0.1, 10, throw="False")
    with pytest.raises(ValueError, match="throw must be True or False"):
        nh.integrate_adaptive(QUARTIC.adapted, x0, 1.0, throw="False")
    run = jax.jit(lambda n: nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, n, max_steps=40, throw=False))
    for n in (0, 41):
        solution = run(n)
        assert solution.result == nh.RESULTS.invalid_n_steps
        assert not bool(jnp.any(jnp.isfinite(solution.ys[1:])))
    assert run(40).result == nh.RESULTS.successful
    with pytest.raises(Exception, match=r"n_steps must lie in \[1, max_steps\]"):
        jax.jit(lambda n: nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, n, max_steps=40).ys)(0)


def test_under_jit_and_with_a_progress_bar(capsys):
    x0 = QUARTIC.initial_state(0.5)
    jitted = jax.jit(lambda x0, dt: nh.integrate(QUARTIC.adapted, METHOD, x0, dt, 30).ys)
    plain = nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 30, progress=True)
    np.testing.assert_allclose(jitted(x0, 0.1), plain.ys, rtol=1e-14, atol=1e-14)
    assert "100.00%" in capsys.readouterr().err


def _rotation(x, args):
    del x, args
    return jnp.array([[0.0, 1.0], [-1.0, 0.0]])


def test_shape_errors_name_the_problem():
    oscillator = nh.SkewGradientSystem(lambda x, args: 0.5 * x @ x, _rotation)
    with pytest.raises(ValueError, match="1-D"):
        nh.integrate(oscillator, METHOD, jnp.ones((2, 2)), 0.1, 10)
    with pytest.raises(ValueError, match="floating"):
        nh.integrate(oscillator, METHOD, jnp.array([1, 0]), 0.1, 10)
    with pytest.raises(ValueError, match=r"\(3, 3\) matrix"):
        nh.integrate(oscillator, METHOD, jnp.ones(3), 0.1, 10)
    vector_energy = nh.SkewGradientSystem(lambda x, args: x, _rotation)
    with pytest.raises(ValueError, match="scalar"):
        nh.integrate(vector_energy, METHOD, jnp.ones(2), 0.1, 10)


def test_argument_errors():
    oscillator = nh.SkewGradientSystem(lambda x, args: 0.5 * x @ x, _rotation)
    x0 = jnp.array([1.0, 0.0])
    for dt in (0.0, -0.1):
        with pytest.raises(ValueError, match="dt must be positive"):
            nh.integrate(oscillator, METHOD, x0, dt, 10)
    with pytest.raises(ValueError, match="n_steps"):
        nh.integrate(oscillator, METHOD, x0, 0.1, 10.0)
    with pytest.raises(ValueError, match="must divide"):
        nh.integrate(oscillator, METHOD, x0, 0.1, 10, save_every=3)


def test_traced_invalid_dt_gets_a_result_code():
    oscillator = nh.SkewGradientSystem(lambda x, args: 0.5 * x @ x, _rotation)
    run = jax.jit(lambda dt: nh.integrate(oscillator, METHOD, jnp.array([1.0, 0.0]), dt, 10, throw=False).result)
    assert run(-0.1) == nh.RESULTS.invalid_dt
    assert run(jnp.inf) == nh.RESULTS.invalid_dt
    assert run(0.1) == nh.RESULTS.successful
    with pytest.raises(Exception, match="dt must be positive"):
        jax.jit(lambda dt: nh.integrate(oscillator, METHOD, jnp.array([1.0, 0.0]), dt, 10).ys)(-0.1)


def test_structure_that_is_not_skew():
    symmetric = nh.SkewGradientSystem(lambda x, args: 0.5 * x @ x, lambda x, args: jnp.eye(2))
    with pytest.raises(Exception, match="not skew-symmetric"):
        nh.integrate(symmetric, METHOD, jnp.array([1.0, 0.0]), 0.1, 10)
    solution = nh.integrate(symmetric, METHOD, jnp.array([1.0, 0.0]), 0.1, 10, throw=False)
    assert solution.result == nh.RESULTS.structure_not_skew
    assert not bool(jnp.any(jnp.isfinite(solution.ys[1:])))


def test_nonfinite_initial_state():
    x0 = QUARTIC.initial_state(0.5).at[3].set(jnp.nan)
    with pytest.raises(Exception, match="initial state contains NaN"):
        nh.integrate(QUARTIC.adapted, METHOD, x0, 0.1, 10)


def _fragile_oscillator():
    """A rotation in the plane whose energy is undefined for x0 > 2: orbits of radius
    above 2 reach it after a few steps, smaller ones never do."""
    hamiltonian = lambda x, args: 0.5 * x @ x + jnp.sqrt(2.0 - x[0]) - jnp.sqrt(2.0 - x[0])  # noqa: E731
    return nh.SkewGradientSystem(hamiltonian, _rotation)


def test_one_failing_trajectory_does_not_spoil_the_batch():
    system = _fragile_oscillator()
    states = jnp.array([[0.0, 1.0], [0.0, 3.0], [0.5, 0.5]])
    run = lambda x0: nh.integrate(system, METHOD, x0, 0.1, 60, throw=False)  # noqa: E731
    batch = jax.vmap(run)(states)
    np.testing.assert_array_equal(batch.result == nh.RESULTS.successful, [True, False, True])
    for i in (0, 2):
        np.testing.assert_allclose(batch.ys[i], run(states[i]).ys, rtol=1e-14, atol=1e-15)
    failed = np.asarray(batch.ys[1])
    finite_rows = np.all(np.isfinite(failed), axis=1)
    first_bad = int(np.argmin(finite_rows))
    assert 1 < first_bad < 60 and not finite_rows[first_bad:].any()
    with pytest.raises(Exception, match="non-finite|not solved to tolerance|singular"):
        nh.integrate(system, METHOD, states[1], 0.1, 60)


def test_root_find_failure_is_reported():
    x0 = QUARTIC.initial_state(0.5)
    starved = nh.DiscreteGradient(root_find_max_steps=1)
    solution = nh.integrate(QUARTIC.adapted, starved, x0, 0.1, 10, throw=False)
    assert solution.result == nh.RESULTS.root_find_not_converged
    assert "root_find_max_steps" in nh.RESULTS[solution.result]
    with pytest.raises(Exception, match="not solved to tolerance"):
        nh.integrate(QUARTIC.adapted, starved, x0, 0.1, 10)


def test_solution_is_a_pytree():
    solution = nh.integrate(QUARTIC.adapted, METHOD, QUARTIC.initial_state(0.5), 0.1, 5)
    assert isinstance(solution, eqx.Module)
    assert len(jax.tree.leaves(solution)) >= 5


DISK = nh.examples.rolling_disk()
GEARBOX = nh.examples.gearbox()


def test_adaptive_index1_solution_matches_the_rolling_disk_exact_solution():
    """The baseline, and the reference of every convergence test: Dopri8 on the index-1
    ODE at tight tolerance against the disk's closed-form motion, at several times."""
    x0 = DISK.initial_state(x1=0.3, theta=0.2, rho1=1.5, rho2=0.7)
    times = jnp.array([0.0, 2.5, 5.0, 10.0])
    solution = nh.integrate_adaptive(
        DISK.canonical, DISK.from_adapted(x0), 10.0, DISK.args, save_at=times, rtol=1e-12, atol=1e-12
    )
    assert solution.result == nh.RESULTS.successful
    exact = jax.vmap(lambda t: jnp.concatenate(DISK.from_adapted(DISK.exact_solution(t, x0))))(times)
    np.testing.assert_allclose(jnp.concatenate(solution.ys, axis=1), exact, atol=1e-9)
    assert solution.energy.shape == (4,) and solution.constraint.shape == (4, 2)
    assert int(solution.stats["num_steps"]) > 0


def test_fixed_step_tsit5_baseline_is_fifth_order_and_preserves_neither_invariant():
    y0 = GEARBOX.random_initial_state(jax.random.key(3))
    t1 = 5.0
    reference = nh.integrate_adaptive(GEARBOX.canonical, y0, t1, rtol=1e-13, atol=1e-13)
    step_sizes = [0.1, 0.05, 0.025]
    final = jax.tree.map(lambda y: y[-1], reference.ys)
    errors = final_state_errors(GEARBOX.canonical, diffrax.Tsit5(), y0, t1, step_sizes, final)
    slope = np.polyfit(np.log(step_sizes), np.log(errors), 1)[0]
    # Still a little pre-asymptotic at these steps (error ratios 60, then 40, toward 32).
    assert 4.5 <= slope <= 6.0, errors
    long = nh.integrate(GEARBOX.canonical, diffrax.Tsit5(), y0, 0.2, 5_000, save_every=50)
    assert float(jnp.max(jnp.abs(long.energy / long.energy[0] - 1))) > 1e-10
    assert float(jnp.max(jnp.abs(long.constraint))) > 1e-10


def test_adaptive_takes_its_method_by_the_name_integrate_uses():
    """method= as in nhjax.integrate; the old solver= still works for a release, with a
    DeprecationWarning, and the same run; both at once is refused."""
    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    new = nh.integrate_adaptive(GEARBOX.canonical, y0, 1.0, method=diffrax.Tsit5(), rtol=1e-8, atol=1e-8)
    with pytest.warns(DeprecationWarning, match="solver= is now method="):
        old = nh.integrate_adaptive(GEARBOX.canonical, y0, 1.0, solver=diffrax.Tsit5(), rtol=1e-8, atol=1e-8)
    np.testing.assert_array_equal(old.ys[0], new.ys[0])
    default = nh.integrate_adaptive(GEARBOX.canonical, y0, 1.0, rtol=1e-8, atol=1e-8)
    assert int(default.stats["num_steps"]) != int(new.stats["num_steps"])  # Dopri8, not Tsit5
    with pytest.raises(TypeError, match="takes the method once"):
        nh.integrate_adaptive(GEARBOX.canonical, y0, 1.0, method=diffrax.Tsit5(), solver=diffrax.Tsit5())


def test_adaptive_baseline_bad_input_and_result_codes():
    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    with pytest.raises(ValueError, match="t1 must be after t0"):
        nh.integrate_adaptive(GEARBOX.canonical, y0, 0.0)
    with pytest.raises(ValueError, match="rtol and atol"):
        nh.integrate_adaptive(GEARBOX.canonical, y0, 1.0, rtol=0.0)
    # A name for a method, and an nhjax method, which has no error estimate to adapt by.
    with pytest.raises(ValueError, match="method must be a diffrax solver such as diffrax.Dopri8"):
        nh.integrate_adaptive(GEARBOX.canonical, y0, 1.0, method="dopri8")
    for fixed_steps in (nh.GonzalezR(), nh.Composition(nh.GonzalezR(), 4)):
        with pytest.raises(ValueError, match=f"{type(fixed_steps).__name__} takes fixed steps: run it with nhjax.integrate"):
            nh.integrate_adaptive(GEARBOX.canonical, y0, 1.0, method=fixed_steps)
    with pytest.raises(ValueError, match="method must be an nhjax method such as nhjax.GonzalezR.. or a diffrax solver, got 'gonzalez-r'"):
        nh.integrate(GEARBOX.canonical, "gonzalez-r", y0, 0.1, 3)
    for save_at, message in [([0.0, 2.0], "inside"), ([-0.5, 1.0], "inside"), ([0.5, 0.2], "sorted"), ([0.0, float("nan")], "finite")]:
        for throw in (True, False):
            with pytest.raises(ValueError, match=message):
                nh.integrate_adaptive(GEARBOX.canonical, y0, 1.0, save_at=jnp.array(save_at), throw=throw)
    violating = (y0[0], y0[1] + 1.0)
    solution = nh.integrate_adaptive(GEARBOX.canonical, violating, 1.0, throw=False)
    assert solution.result == nh.RESULTS.constraint_violated_initially
    # A start that fails is not integrated: no step is tried (from its NaN state the
    # controller would reject steps up to max_steps), and the save times are the ones asked.
    assert int(solution.stats["num_steps"]) == 0 and int(solution.stats["num_rejected_steps"]) == 0
    np.testing.assert_array_equal(solution.ts, [0.0, 1.0])
    assert not np.isfinite(np.asarray(solution.ys[0])).any()
    with pytest.raises(Exception, match="constraint"):
        nh.integrate_adaptive(GEARBOX.canonical, violating, 1.0)
    too_few = nh.integrate_adaptive(GEARBOX.canonical, y0, 100.0, max_steps=5, throw=False)
    assert too_few.result != nh.RESULTS.successful
    batch = jax.vmap(lambda q, p: nh.integrate_adaptive(GEARBOX.canonical, (q, p), 1.0, throw=False).result)(
        jnp.stack([y0[0], violating[0]]), jnp.stack([y0[1], violating[1]])
    )
    np.testing.assert_array_equal(batch == nh.RESULTS.successful, [True, False])
    np.testing.assert_array_equal(batch == nh.RESULTS.constraint_violated_initially, [False, True])


def test_a_sweep_of_traced_tolerances_compiles_once():
    """Tighter traced tolerances, one compiled program: more steps, smaller errors
    against the tightest; a traced tolerance that is not positive gets a code."""
    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    run = jax.jit(lambda tol: nh.integrate_adaptive(GEARBOX.canonical, y0, 5.0, rtol=tol, atol=tol, throw=False))
    reference = nh.integrate_adaptive(GEARBOX.canonical, y0, 5.0, rtol=1e-12, atol=1e-12).ys[0][-1]
    errors, steps = [], []
    for tol in (1e-4, 1e-6, 1e-8):
        solution = run(tol)
        assert solution.result == nh.RESULTS.successful
        errors.append(float(jnp.max(jnp.abs(solution.ys[0][-1] - reference))))
        steps.append(int(solution.stats["num_steps"]))
    assert run._cache_size() == 1
    assert steps[0] < steps[1] < steps[2] and errors[0] > errors[1] > errors[2]
    for bad in (0.0, -1e-6, jnp.nan):
        assert run(bad).result == nh.RESULTS.invalid_tolerance


def test_a_diffrax_solver_that_blows_up_gets_a_result_code():
    """Explicit Euler far beyond its stability limit overflows to inf and NaN: a
    fixed-step diffrax solver does not report that itself, nh.integrate does."""
    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    solution = nh.integrate(GEARBOX.canonical, diffrax.Euler(), y0, 50.0, 400, save_every=400, throw=False)
    assert solution.result == nh.RESULTS.nonfinite_step
    with pytest.raises(Exception, match="finite"):
        nh.integrate(GEARBOX.canonical, diffrax.Euler(), y0, 50.0, 400, save_every=400)


def _gearbox_start():
    q0 = jnp.array([0.9, -0.4, 0.3])
    return q0, GEARBOX.canonical.project_momentum(q0, jnp.array([-0.3, 1.0, 0.5]))


def test_an_overflowing_energy_is_a_failure_even_while_the_states_are_finite():
    """Tsit5 at h = 100 on the gearbox: the states reach 1e189, still finite, while the
    energy overflows to inf. That save and every one after are NaN, with the code."""
    solution = nh.integrate(GEARBOX.canonical, diffrax.Tsit5(), _gearbox_start(), 100.0, 10, throw=False)
    assert solution.result == nh.RESULTS.nonfinite_step
    finite = np.isfinite(np.asarray(solution.energy))
    first_bad = int(np.argmin(finite))
    assert first_bad > 0 and not finite[first_bad:].any()
    assert not np.isfinite(np.asarray(solution.ys[0][first_bad:])).any()
    assert np.isfinite(np.asarray(solution.ys[0][:first_bad])).all()
    with pytest.raises(RuntimeError, match=r"nhjax.integrate failed: the save at t = \d+ is not finite .*non-finite state, energy"):
        nh.integrate(GEARBOX.canonical, diffrax.Tsit5(), _gearbox_start(), 100.0, 10)


def test_the_error_names_the_step_and_time_of_the_failure():
    starved = nh.GonzalezF(root_find_max_steps=2)
    with pytest.raises(RuntimeError, match=r"failed at step 1 of 10 \(t = 0 to 2\): The implicit equations"):
        nh.integrate(GEARBOX.canonical, starved, _gearbox_start(), 2.0, 10)
    with pytest.raises(RuntimeError, match="could not start: The initial momentum violates"):
        q0, p0 = _gearbox_start()
        nh.integrate(GEARBOX.canonical, starved, (q0, p0 + 1.0), 2.0, 10)


def test_step_sizes_and_times_that_cannot_be_stepped():
    oscillator = nh.SkewGradientSystem(lambda x, args: 0.5 * x @ x, _rotation)
    x0 = jnp.array([1.0, 0.0])
    for dt in (jnp.inf, -jnp.inf, jnp.nan, 0.0):
        with pytest.raises(ValueError, match="dt must be positive and finite"):
            nh.integrate(oscillator, METHOD, x0, float(dt), 10)
    for t0 in (jnp.nan, jnp.inf):
        with pytest.raises(ValueError, match="t0 must be finite"):
            nh.integrate(oscillator, METHOD, x0, 0.1, 10, t0=float(t0))
    # 1e20 + 0.1 == 1e20: the steps would not advance.
    solution = nh.integrate(oscillator, METHOD, x0, 0.1, 10, t0=1e20, throw=False)
    assert solution.result == nh.RESULTS.invalid_t0
    with pytest.raises(RuntimeError, match="t0 \\+ k dt must be finite and strictly increasing"):
        nh.integrate(oscillator, METHOD, x0, 0.1, 10, t0=1e20)
    # 1e6 + k 1e-9 increases, but each step is within diffrax's end clipping (100 ulps
    # of the end time), which would end the run early: refused rather than cut short.
    assert nh.integrate(oscillator, METHOD, x0, 1e-9, 10, t0=1e6, throw=False).result == nh.RESULTS.invalid_t0
    assert nh.integrate(oscillator, METHOD, x0, 1e-6, 10, t0=1e6, throw=False).result == nh.RESULTS.successful
    traced = jax.jit(lambda t0: nh.integrate(oscillator, METHOD, x0, 0.1, 10, t0=t0, throw=False).result)
    assert traced(jnp.nan) == nh.RESULTS.invalid_t0
    assert traced(1.0) == nh.RESULTS.successful
    assert traced(-0.5) == nh.RESULTS.successful  # through t = 0
    # Within a bound, the times of the steps taken count, not those of the bound.
    bounded = jax.jit(lambda t0, n: nh.integrate(oscillator, METHOD, x0, 0.1, n, t0=t0, max_steps=10**6, save_every=10**6, throw=False).result)
    assert bounded(1e20, 10) == nh.RESULTS.invalid_t0
    assert bounded(1.0, 10) == nh.RESULTS.successful


def test_nonfinite_parameters_are_named():
    sleigh = nh.examples.chaplygin_sleigh()
    x0 = sleigh.initial_state()
    with pytest.raises(ValueError, match=r"args\['J'\] is not finite"):
        nh.integrate(sleigh.adapted, METHOD, x0, 0.5, 10, args=dict(sleigh.args, J=jnp.nan))
    with pytest.raises(ValueError, match=r"args\['m'\] is not finite"):
        nh.integrate(sleigh.canonical, nh.SIDLA(), sleigh.from_adapted(x0), 0.5, 10, args=dict(sleigh.args, m=jnp.inf))
    traced = jax.jit(lambda m: nh.integrate(sleigh.adapted, METHOD, x0, 0.5, 10, args=dict(sleigh.args, m=m), throw=False).result)
    assert traced(jnp.inf) == nh.RESULTS.nonfinite_args
    # A negative mass under a square root: the structure is NaN at the start.
    assert traced(-1.0) == nh.RESULTS.nonfinite_initial_evaluation
    assert traced(1.0) == nh.RESULTS.successful
    with pytest.raises(ValueError, match="m must be positive and finite, got m=-1"):
        nh.examples.chaplygin_sleigh(m=-1.0)
    with pytest.raises(ValueError, match="J_phi must be positive"):
        nh.examples.rolling_disk(J_phi=0.0)
    with pytest.raises(ValueError, match="I22 must be positive"):
        nh.examples.suslov(I22=jnp.nan)


def test_an_example_without_its_args_says_what_it_needs():
    sleigh = nh.examples.chaplygin_sleigh()
    with pytest.raises(ValueError, match="Chaplygin sleigh's functions read the parameters J, a, m from args"):
        nh.integrate(sleigh.adapted, METHOD, sleigh.initial_state(), 0.5, 10)
    disk = nh.examples.rolling_disk()
    with pytest.raises(ValueError, match="rolling disk's functions read the parameters m, r, J_theta, J_phi"):
        nh.integrate(disk.canonical, nh.SIDLA(), disk.from_adapted(disk.initial_state()), 0.1, 10, args={"m": 1.0})


def test_states_and_step_counts_of_the_wrong_kind():
    q0, p0 = _gearbox_start()
    with pytest.raises(ValueError, match="q must be a 1-D array, got a list \\(convert it with jnp.asarray\\)"):
        nh.integrate(GEARBOX.canonical, nh.SIDLA(), ([0.9, -0.4, 0.3], p0), 0.1, 10)
    with pytest.raises(ValueError, match="SkewGradientSystem must be a 1-D array, got a tuple"):
        nh.integrate(QUARTIC.adapted, METHOD, (QUARTIC.initial_state(0.5),), 0.1, 10)
    with pytest.raises(ValueError, match="n_steps must be a positive int, got True"):
        nh.integrate(GEARBOX.canonical, nh.SIDLA(), (q0, p0), 0.1, True)


def test_adaptive_tolerances_follow_the_dtype():
    """float32: the default tolerance is 100 eps, not float64's 1e-12, which float32's
    rounding cannot meet (the controller would shrink the steps without end)."""
    double = GEARBOX.random_initial_state(jax.random.key(0))
    y0 = jax.tree.map(lambda y: y.astype(jnp.float32), double)
    solution = nh.integrate_adaptive(GEARBOX.canonical, y0, 10.0)
    assert solution.result == nh.RESULTS.successful
    assert int(solution.stats["num_steps"]) < 2000
    reference = nh.integrate_adaptive(GEARBOX.canonical, double, 10.0)
    for single, double in zip(solution.ys, reference.ys):
        np.testing.assert_allclose(single[-1], double[-1], atol=1e-3)


def test_float64_parameters_of_a_float32_run_are_cast_to_float32():
    """A float32 state with float64 parameters in `args` (arrays, as from a float64
    fit): the run stays float32, the same to the bit as with the parameters cast by
    hand, at fixed and at adaptive steps. Uncast, a step promoted the state to float64
    and the loop's float32 buffers refused it with an error naming neither."""

    def hamiltonian(q, p, args):
        return 0.5 * p @ p + 0.5 * args["stiffness"] * (q[0] ** 2 + q[1] ** 2) + jnp.cos(q[2])

    system = nh.NonholonomicSystem(hamiltonian, GEARBOX.canonical.constraints)
    y0 = jax.tree.map(lambda y: y.astype(jnp.float32), GEARBOX.random_initial_state(jax.random.key(0)))
    wide, narrow = {"stiffness": jnp.asarray(1.5, jnp.float64)}, {"stiffness": jnp.asarray(1.5, jnp.float32)}
    for run in (
        lambda args: nh.integrate(system, nh.GonzalezR(), y0, 0.1, 20, args=args, save_every=20),
        lambda args: nh.integrate_adaptive(system, y0, 1.0, args=args),
    ):
        cast, by_hand = run(wide), run(narrow)
        assert cast.ys[0].dtype == cast.energy.dtype == jnp.float32
        for got, want in zip(jax.tree.leaves(cast.ys), jax.tree.leaves(by_hand.ys)):
            np.testing.assert_array_equal(got, want)


def test_the_readme_lists_every_code_nhjax_sets():
    """Each code nhjax defines, and the adaptive loop's max_steps_reached, has a row in
    the README's Errors table."""
    readme = (pathlib.Path(__file__).parents[1] / "README.md").read_text()
    table = readme[readme.index("### Errors"):]
    own = set(nh.RESULTS._name_to_item) - set(diffrax.RESULTS._name_to_item)
    for name in sorted(own | {"successful", "max_steps_reached"}):
        assert f"| `{name}` |" in table, name


def _loop_cases():
    """(system, method, start, dt, n_steps, args, max_steps) for each kind of run the
    two loops string together: tuple and array states, an nhjax method, a composition,
    a wrapped diffrax solver and a plain one, a forced system's ledger, a batch in which
    one trajectory fails, and a traced number of steps up to a bound."""
    gearbox = nh.examples.gearbox()
    q0, p0 = gearbox.start("canonical")
    drive = nh.examples.differential_drive()
    suslov = nh.examples.suslov()
    return {
        "one of two failing": (_fragile_oscillator(), METHOD, jnp.array([[0.0, 1.0], [0.0, 3.0]]), 0.1, 40, None, None),
        "GONZALEZ-R, 17 of 24 steps": (gearbox.canonical, nh.GonzalezR(), (q0, p0), 0.1, 17, gearbox.args, 24),
        "composition": (gearbox.canonical, nh.Composition(nh.GonzalezR(), 4), (q0, p0), 0.2, 12, gearbox.args, None),
        "projected Dopri8": (gearbox.canonical, nh.Projection(diffrax.Dopri8()), (q0, p0), 0.2, 12, gearbox.args, None),
        "Tsit5": (gearbox.canonical, diffrax.Tsit5(), (q0, p0), 0.2, 12, gearbox.args, None),
        "forced": (drive.canonical, nh.GonzalezR(), drive.start("canonical"), 0.05, 12, drive.args, None),
        "GONZALEZ, adapted": (suslov.adapted, nh.DiscreteGradient(), suslov.start("adapted"), 0.1, 12, suslov.args, None),
    }


@pytest.mark.parametrize("case", list(_loop_cases()))
def test_nhjax_loop_and_diffrax_loop_return_the_same_run(case):
    """`nhjax.integrate` strings the steps together by its own loop, and by
    `diffrax.diffeqsolve` where a diffrax adjoint asks for it: the same states, save
    times, energies, codes and step counts, NaN and infinite in the same places after a
    failure. Finite values agree to roundoff and root-finder iterations nearly: two
    programs compiled apart may round differently, and an iteration near the
    tolerance may then stop one iteration apart."""
    system, method, y0, dt, n_steps, args, max_steps = _loop_cases()[case]

    def run(y0, adjoint):
        return nh.integrate(
            system, method, y0, dt, n_steps, args=args, save_every=4 if max_steps else 2,
            throw=False, adjoint=adjoint, max_steps=max_steps,
        )

    batched = case == "one of two failing"
    if batched:
        run = jax.vmap(run, (0, None))
    own, theirs = run(y0, None), run(y0, diffrax.RecursiveCheckpointAdjoint())
    if batched:
        np.testing.assert_array_equal(own.result == nh.RESULTS.successful, [True, False])
        assert 1 < int(own.stats["num_steps"][1]) < n_steps
    else:
        assert own.result == nh.RESULTS.successful
    assert jax.tree.structure(own) == jax.tree.structure(theirs)
    iterations = {"root_find_steps", "max_root_find_steps", "substep_root_find_steps"}
    for name in iterations & {name for name, value in own.stats.items() if value is not None}:
        got, want = np.asarray(own.stats[name]), np.asarray(theirs.stats[name])
        np.testing.assert_allclose(got, want, rtol=0.05, atol=1)
    own, theirs = (eqx.tree_at(lambda s: s.stats, s, {k: v for k, v in s.stats.items() if k not in iterations}) for s in (own, theirs))
    for got, want in zip(jax.tree.leaves(own), jax.tree.leaves(theirs)):
        got, want = np.asarray(got), np.asarray(want)
        assert got.shape == want.shape and got.dtype == want.dtype
        if not np.issubdtype(want.dtype, np.floating):
            np.testing.assert_array_equal(got, want)
            continue
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
        finite = np.isfinite(want)
        np.testing.assert_allclose(got[finite], want[finite], rtol=1e-13, atol=1e-14)
