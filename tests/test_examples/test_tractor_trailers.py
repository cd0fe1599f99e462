"""The tractor with trailers against what is derived here from the bodies' positions
alone: its metric, potential and constraints; the lone tractor against the knife edge's
closed form; the train against its reduced equations in the tractor's speed and turning
rate (Lagrange--d'Alembert with the velocities eliminated), integrated by Dopri8."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import nhjax as nh
from nhjax._linalg import SPD_UNROLL_LIMIT
from tests.helpers import relative_energy_error


def _positions(example, q):
    """The axle midpoints P_0..P_N, each hitched at `hitch` behind the one ahead."""
    steps = -example.hitch * jnp.stack([jnp.cos(q[3:]), jnp.sin(q[3:])], axis=1)
    return jnp.concatenate([q[None, :2], q[None, :2] + jnp.cumsum(steps, axis=0)])


def _axle_velocities(example, q, qdot):
    """The velocities of P_0..P_N along qdot."""
    return jax.jvp(lambda z: _positions(example, z), (q,), (qdot,))[1]


def _masses(example):
    return jnp.array([example.m_tractor] + [example.m_trailer] * example.trailers)


def _kinetic_energy(example, q, qdot):
    velocities = _axle_velocities(example, q, qdot)
    inertias = jnp.array([example.J_tractor] + [example.J_trailer] * example.trailers)
    return 0.5 * _masses(example) @ jnp.sum(velocities**2, axis=1) + 0.5 * inertias @ qdot[2:] ** 2


def _potential(example, q):
    return -example.g * np.sin(example.slope) * _masses(example) @ _positions(example, q)[:, 0]


def _sideways_velocities(example, q, qdot):
    """Each axle's velocity across its heading: zero when no wheel slips."""
    velocities = _axle_velocities(example, q, qdot)
    headings = q[2:]
    return -jnp.sin(headings) * velocities[:, 0] + jnp.cos(headings) * velocities[:, 1]


def test_metric_potential_and_constraints_are_those_of_the_bodies():
    example = nh.examples.tractor_trailers(4, m_trailer=0.7, J_trailer=0.15, hitch=0.8, slope=0.3)
    keys = jax.random.split(jax.random.key(0), 2)
    q = jax.random.normal(keys[0], (7,))
    qdot = jax.random.normal(keys[1], (7,))
    metric = jax.hessian(lambda v: _kinetic_energy(example, q, v))(qdot)
    np.testing.assert_allclose(example.metric(q, example.args), metric, rtol=0, atol=1e-14)
    np.testing.assert_allclose(example.potential(q, example.args), _potential(example, q), rtol=1e-14)
    np.testing.assert_allclose(
        example.constraints(q, example.args) @ qdot, _sideways_velocities(example, q, qdot), rtol=0, atol=1e-14
    )
    # The trailers' kinematics allows exactly the motions that slip nowhere.
    allowed = example.velocity(q, 1.3, -0.4)
    assert float(jnp.max(jnp.abs(_sideways_velocities(example, q, allowed)))) < 1e-14
    assert np.linalg.matrix_rank(np.asarray(example.constraints(q, example.args))) == 5


def _second_order_errors(example, system, y0, t1, step_counts, observed, expected, tolerance):
    """GONZALEZ-R's distances at `t1` of `observed(q, p)` from `expected`, for each step
    count (one program for all: `n_steps` traced up to a bound), checked to fall at
    second order, with the energy and the constraint within `tolerance` at every save."""
    bound = max(step_counts)
    run = jax.jit(lambda h, n: nh.integrate(
        system, nh.GonzalezR(), y0, h, n, args=example.args, max_steps=bound, save_every=bound
    ))
    errors = []
    for steps in step_counts:
        solution = run(t1 / steps, steps)
        errors.append(np.max(np.abs(observed(*(y[-1] for y in solution.ys)) - expected)))
        assert relative_energy_error(solution) < tolerance
        assert float(jnp.max(jnp.abs(solution.constraint))) < tolerance
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all((orders > 1.8) & (orders < 2.3)), (errors, orders)
    return errors


def test_the_lone_tractor_rolls_as_the_knife_edge_on_an_inclined_plane():
    """The form from the Lagrangian: errors at t = 2 against the closed form fall at
    second order, and the energy and constraint stay at roundoff."""
    example = nh.examples.tractor_trailers(0)
    speed, turn_rate, t1 = 0.5, 0.8, 2.0
    q0, p0 = example.initial_state(speed=speed, turn_rate=turn_rate)
    exact = example.lone_tractor(t1, speed, turn_rate)
    system = example.canonical_from_lagrangian

    def observed(q, p):
        velocity = system.velocity(q, p, example.args)
        speed_now = velocity[:2] @ jnp.array([jnp.cos(q[2]), jnp.sin(q[2])])
        return np.concatenate([np.asarray(q), [speed_now, velocity[2]]])

    errors = _second_order_errors(example, system, (q0, p0), t1, (20, 40, 80), observed, exact, 1e-14)
    assert errors[-1] < 3e-5


def _reduced_equations(example):
    r"""$(q, \nu)' $ with $\nu$ = (tractor speed, turning rate), $\dot q = S(q)\nu$
    (`TractorTrailers.velocity`), and $S^T(M\ddot q + \dot M\dot q - \partial_qT
    + \partial_qV) = 0$: the constraint forces, normal to $S$, drop out. $T$ and $V$
    from the bodies' positions."""

    def kinematics(q, nu):
        return example.velocity(q, nu[0], nu[1])

    def momentum(q, qdot):
        return jax.grad(lambda v: _kinetic_energy(example, q, v))(qdot)

    def field(t, state, args):
        del t, args
        q, nu = state[:-2], state[-2:]
        frame = jax.jacfwd(lambda v: kinematics(q, v))(nu)
        qdot = frame @ nu
        metric = jax.jacfwd(lambda v: momentum(q, v))(qdot)
        frame_rate = jax.jvp(lambda z: jax.jacfwd(lambda v: kinematics(z, v))(nu), (q,), (qdot,))[1]
        momentum_rate = jax.jvp(lambda z: momentum(z, qdot), (q,), (qdot,))[1]
        force = jax.grad(lambda z: _kinetic_energy(example, z, qdot) - _potential(example, z))(q)
        rhs = -frame.T @ (metric @ frame_rate @ nu + momentum_rate - force)
        return jnp.concatenate([qdot, jnp.linalg.solve(frame.T @ metric @ frame, rhs)])

    return field


def test_the_train_converges_to_its_reduced_equations_at_second_order():
    """Three trailers to t = 2: GONZALEZ-R in canonical coordinates against Dopri8 on
    the reduced equations at 1e-13, errors of positions and velocities falling at
    second order; energy and constraints at roundoff; and the tractor, which no force turns about its axle's
    midpoint, keeps its turning rate."""
    example = nh.examples.tractor_trailers(3)
    speed, turn_rate, t1 = 1.0, 0.3, 2.0
    q0, p0 = example.initial_state(speed=speed, turn_rate=turn_rate)
    reference = diffrax.diffeqsolve(
        diffrax.ODETerm(_reduced_equations(example)), diffrax.Dopri8(), 0.0, t1, 0.01,
        jnp.concatenate([q0, jnp.array([speed, turn_rate])]),
        stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13), max_steps=100_000,
    ).ys[-1]
    q1, (speed1, turn_rate1) = reference[:-2], reference[-2:]
    expected = np.concatenate([np.asarray(q1), np.asarray(example.velocity(q1, speed1, turn_rate1))])
    assert abs(float(q1[2]) - turn_rate * t1) < 1e-12 and abs(float(turn_rate1) - turn_rate) < 1e-12

    system = example.canonical

    def observed(q, p):
        return np.concatenate([np.asarray(q), np.asarray(system.velocity(q, p, example.args))])

    errors = _second_order_errors(example, system, (q0, p0), t1, (25, 50, 100), observed, expected, 1e-13)
    assert errors[-1] < 1e-5


def test_a_train_longer_than_the_unrolled_solves_keeps_its_invariants():
    """Seven trailers (n = 10, k = 8): its metric and the constraints' Gram matrix are
    solved by LAPACK's Cholesky (`nhjax._linalg.SPD_UNROLL_LIMIT`), not by the unrolled
    elimination. The velocity is the metric's solve, and GONZALEZ-R keeps the energy and
    the constraints at roundoff."""
    example = nh.examples.tractor_trailers(7)
    system = example.canonical
    q0, p0 = example.initial_state()
    assert min(q0.shape[0], q0.shape[0] - 2) > SPD_UNROLL_LIMIT
    np.testing.assert_allclose(
        system.velocity(q0, p0, example.args), np.linalg.solve(example.metric(q0, example.args), p0), rtol=1e-13, atol=1e-15
    )
    solution = nh.integrate(system, nh.GonzalezR(), (q0, p0), 0.05, 20, args=example.args)
    assert relative_energy_error(solution) < 1e-13
    assert float(jnp.max(jnp.abs(solution.constraint))) < 1e-13
