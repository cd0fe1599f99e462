"""Systems with a dissipation and a force: their equations, energy balance and input
checks along the reference route, `integrate_adaptive` (the fixed-step methods with
them: `tests/test_forced_methods.py`)."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate

import nhjax as nh


DISK = nh.examples.rolling_disk()
TIGHT = dict(rtol=1e-12, atol=1e-12)
TIMES = jnp.linspace(0.0, 5.0, 11)


def _damping(q, p, args):
    """State-dependent Rayleigh damping on the heading and the rolling angle."""
    return jnp.diag(jnp.array([0.0, 0.0, 0.3, 0.2])) * (1 + q[2] ** 2)


def _torques(t, q, p, args):
    """A steering torque varying in time and a constant drive on the wheel."""
    return jnp.array([0.0, 0.0, jnp.sin(t), 0.5])


def _forced_disk(dissipation=_damping, force=_torques):
    return nh.NonholonomicSystem(DISK.canonical.hamiltonian, DISK.canonical.constraints, dissipation, force)


def test_the_energy_balance_holds_along_the_index_1_flow():
    """dH/dt = v^T F - v^T D v: the saved energy change equals the integrated work less
    the dissipated energy, the dissipated energy never decreases, and the constraint
    holds to the tolerance."""
    system = _forced_disk()
    solution = nh.integrate_adaptive(system, DISK.start("canonical"), 5.0, DISK.args, save_at=TIMES, **TIGHT)
    balance = solution.energy - solution.energy[0] - (solution.work - solution.dissipated)
    assert float(jnp.max(jnp.abs(balance))) < 1e-9
    assert bool(jnp.all(jnp.diff(solution.dissipated) > 0))
    assert float(solution.dissipated[-1]) > 1 and float(solution.work[-1]) > 1  # both matter here
    assert float(jnp.max(jnp.abs(solution.constraint))) < 1e-9
    conservative = nh.integrate_adaptive(DISK.canonical, DISK.start("canonical"), 5.0, DISK.args, **TIGHT)
    # A conservative run's ledger is zeros, and its balance is its energy conservation.
    assert float(jnp.max(jnp.abs(conservative.work))) == 0.0 and float(jnp.max(jnp.abs(conservative.dissipated))) == 0.0
    assert conservative.work.shape == conservative.energy.shape == conservative.dissipated.shape


def test_the_reduced_form_carries_the_dissipation_and_the_force():
    """Two routes to one motion: the index-1 ODE in (q, p), and the reduced equations
    on (q, rho) with R = diag(0, X^T D X) and g = (0, X^T F), mapped back; the same work
    and dissipation by both."""
    system = _forced_disk()
    y0 = DISK.start("canonical")
    signs = system.frame_signs(y0[0], DISK.args)
    canonical = nh.integrate_adaptive(system, y0, 5.0, DISK.args, save_at=TIMES, **TIGHT)
    reduced = nh.integrate_adaptive(
        system.reduced(signs), system.to_reduced(y0, DISK.args, signs), 5.0, DISK.args, save_at=TIMES, **TIGHT
    )
    mapped = jax.vmap(lambda z: jnp.concatenate(system.from_reduced(z, DISK.args, signs)))(reduced.ys)
    np.testing.assert_allclose(mapped, jnp.concatenate(canonical.ys, axis=1), rtol=0, atol=1e-9)
    np.testing.assert_allclose(reduced.work, canonical.work, rtol=0, atol=1e-9)
    np.testing.assert_allclose(reduced.dissipated, canonical.dissipated, rtol=0, atol=1e-9)


def test_from_lagrangian_takes_them_in_velocities():
    """D(q, qdot) and F(t, q, qdot) of the Lagrangian form are those of the canonical
    form at qdot = dH/dp: the same run."""

    def in_velocities(function):
        # The disk's velocity is K p with K = diag(1/m, 1/m, 1/J_theta, 1/J_phi): p = M qdot.
        def wrapped(*arguments):
            *head, q, qdot, args = arguments
            mass = jnp.array([1.0, 1.0, 0.25, 0.5])
            return function(*head, q, mass * qdot, args)

        return wrapped

    lagrangian = nh.NonholonomicSystem.from_lagrangian(
        DISK.canonical_from_lagrangian.hamiltonian.lagrangian,
        DISK.canonical.constraints,
        dissipation=in_velocities(_damping),
        force=in_velocities(_torques),
    )
    y0 = DISK.start("canonical")
    by_lagrangian = nh.integrate_adaptive(lagrangian, y0, 5.0, DISK.args, **TIGHT)
    by_hamiltonian = nh.integrate_adaptive(_forced_disk(), y0, 5.0, DISK.args, **TIGHT)
    np.testing.assert_allclose(by_lagrangian.ys[1], by_hamiltonian.ys[1], rtol=0, atol=1e-10)
    np.testing.assert_allclose(by_lagrangian.work, by_hamiltonian.work, rtol=0, atol=1e-10)


def test_a_damped_driven_oscillator_against_an_independent_solver():
    """x = (q, p), Pi = J, H = (q^2 + p^2)/2, R = diag(0, c), g = (0, a cos wt): the linear
    ODE q'' + c q' + q = a cos wt, solved by SciPy's DOP853, and its energy balance with
    the work of g and the dissipation c p^2 integrated by the same."""
    c, a, w = 0.3, 0.7, 1.3
    system = nh.SkewGradientSystem(
        lambda x, args: 0.5 * x @ x,
        lambda x, args: jnp.array([[0.0, 1.0], [-1.0, 0.0]], dtype=x.dtype),
        dissipation=lambda x, args: jnp.diag(jnp.array([0.0, c], dtype=x.dtype)),
        force=lambda t, x, args: jnp.stack([jnp.zeros_like(t), a * jnp.cos(w * t)]),
    )
    x0 = jnp.array([1.0, 0.0])
    solution = nh.integrate_adaptive(system, x0, 10.0, save_at=jnp.linspace(0.0, 10.0, 6), **TIGHT)

    def field(t, z):
        q, p, work, dissipated = z
        return [p, -q - c * p + a * np.cos(w * t), p * a * np.cos(w * t), c * p**2]

    reference = scipy.integrate.solve_ivp(
        field, (0.0, 10.0), [1.0, 0.0, 0.0, 0.0], method="DOP853", t_eval=np.linspace(0.0, 10.0, 6), rtol=1e-13, atol=1e-13
    ).y.T
    np.testing.assert_allclose(solution.ys, reference[:, :2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(solution.work, reference[:, 2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(solution.dissipated, reference[:, 3], rtol=0, atol=1e-9)


def test_no_dissipation_and_no_force_is_the_conservative_system():
    plain = DISK.canonical
    explicit = nh.NonholonomicSystem(plain.hamiltonian, plain.constraints, dissipation=None, force=None)
    assert not explicit.is_forced() and explicit == plain
    zero = _forced_disk(dissipation=None, force=lambda t, q, p, args: jnp.zeros_like(q))
    assert zero.is_forced()
    y0 = DISK.start("canonical")
    forced = nh.integrate_adaptive(zero, y0, 5.0, DISK.args, **TIGHT)
    free = nh.integrate_adaptive(plain, y0, 5.0, DISK.args, **TIGHT)
    np.testing.assert_allclose(forced.ys[1], free.ys[1], rtol=0, atol=1e-12)
    assert float(jnp.max(jnp.abs(forced.work))) == 0.0 and float(jnp.max(jnp.abs(forced.dissipated))) == 0.0


def test_bad_dissipation_and_force_are_named():
    y0 = DISK.start("canonical")
    with pytest.raises(ValueError, match=r"dissipation\(q, p, args\) must return shape \(4, 4\), got \(4,\)"):
        nh.integrate_adaptive(_forced_disk(dissipation=lambda q, p, args: q), y0, 1.0, DISK.args)
    with pytest.raises(ValueError, match=r"force\(t, q, p, args\) must return shape \(4,\), got \(3,\)"):
        nh.integrate_adaptive(_forced_disk(force=lambda t, q, p, args: q[:3]), y0, 1.0, DISK.args)
    with pytest.raises(ValueError, match=r"force\(t, q, p, args\) must return the state's dtype float64, got float32"):
        nh.integrate_adaptive(_forced_disk(force=lambda t, q, p, args: q.astype(jnp.float32)), y0, 1.0, DISK.args)
    # One system whose D and F come from args, so that the bad cases share one program.
    configurable = _forced_disk(
        dissipation=lambda q, p, args: args["D"],
        force=lambda t, q, p, args: jnp.where(t > args["nan_after"], jnp.nan, 1.0) * jnp.ones_like(q),
    )
    good = {**DISK.args, "D": jnp.eye(4), "nan_after": 10.0}
    negative = {**good, "D": -jnp.eye(4)}
    asymmetric = {**good, "D": jnp.eye(4).at[0, 1].set(0.5)}
    assert nh.integrate_adaptive(configurable, y0, 1.0, good, throw=False).result == nh.RESULTS.successful
    for args in (negative, asymmetric):
        solution = nh.integrate_adaptive(configurable, y0, 1.0, args, throw=False)
        assert solution.result == nh.RESULTS.dissipation_not_positive_semidefinite
        assert not bool(jnp.any(jnp.isfinite(solution.ys[0][1:])))
        with pytest.raises(RuntimeError, match="not symmetric positive semidefinite"):
            nh.integrate_adaptive(configurable, y0, 1.0, args)
    # A force that turns NaN mid-run: the adaptive loop stops with a failure, not a
    # finite-looking end (diffrax's controller spends max_steps on it first).
    nonfinite = {**good, "nan_after": 0.5}
    failed = nh.integrate_adaptive(configurable, y0, 1.0, nonfinite, throw=False, max_steps=200)
    assert failed.result != nh.RESULTS.successful


def test_projection_outside_a_run_refuses_a_forced_system():
    """A forced system's initial energy level is not an invariant: Projection needs the
    run's ledger to project onto the balance, and says so when diffrax is called
    without it."""
    y0 = DISK.start("canonical")
    with pytest.raises(ValueError, match="projects onto the energy balance"):
        diffrax.diffeqsolve(
            _forced_disk(), nh.Projection(diffrax.Dopri8()), 0.0, 1.0, 0.1, y0, DISK.args
        )


def test_derivatives_with_respect_to_the_force_match_finite_differences():
    """d(final heading, work)/d(drive torque), the torque a parameter in args, by reverse
    mode through the adaptive run, against central differences; and a batch under vmap
    in which one trajectory's dissipation is indefinite: its code, and the others'
    states equal to their single runs."""

    def drive(t, q, p, args):
        return jnp.zeros_like(q).at[2].set(args["steer"] * jnp.sin(t)).at[3].set(args["drive"])

    system = nh.NonholonomicSystem(DISK.canonical.hamiltonian, DISK.canonical.constraints, _damping, drive)
    y0 = DISK.start("canonical")

    def outcome(torque):
        args = {**DISK.args, "steer": 1.0, "drive": torque}
        solution = nh.integrate_adaptive(system, y0, 3.0, args, **TIGHT)
        return solution.ys[0][-1, 2] + solution.work[-1]

    derivative = float(jax.grad(outcome)(0.5))
    step = 1e-5
    difference = (float(outcome(0.5 + step)) - float(outcome(0.5 - step))) / (2 * step)
    assert abs(derivative - difference) <= 1e-7 * max(1.0, abs(difference)), (derivative, difference)

    def run(scale):
        damped = nh.NonholonomicSystem(
            DISK.canonical.hamiltonian, DISK.canonical.constraints, lambda q, p, args: scale * _damping(q, p, args), _torques
        )
        return nh.integrate_adaptive(damped, y0, 2.0, DISK.args, throw=False, **TIGHT)

    batch = jax.vmap(run)(jnp.array([1.0, -1.0, 2.0]))
    assert list(batch.result == nh.RESULTS.dissipation_not_positive_semidefinite) == [False, True, False]
    for index, scale in ((0, 1.0), (2, 2.0)):
        np.testing.assert_allclose(batch.ys[1][index], run(scale).ys[1], rtol=0, atol=1e-12)
