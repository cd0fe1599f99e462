"""Euler's disk (`nhjax.examples.rolling_disk_3d`) against the equations of motion that
`sympy.physics.mechanics.KanesMethod` builds for the same disk from its bodies, frames
and rolling condition, without the example's mass matrix or constraint matrix."""

import pathlib
import sys

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate

import nhjax as nh


sys.path.insert(0, str(pathlib.Path(__file__).parents[2] / "benchmarks"))
from kane import kanes_equations, PARAMETERS  # noqa: E402


DISK = nh.examples.rolling_disk_3d(m=1.3, r=0.7, g=2.0, J_axle=0.4, J_diameter=0.2)
# A generic start: leaning, turning, tipping and spinning.
Q0 = jnp.array([0.3, -0.2, 0.4, 0.25, 0.1])
RATES = dict(turn_rate=0.6, lean_rate=-0.3, spin_rate=2.5)


def _parameters():
    return tuple(DISK.args[name] for name in PARAMETERS)


def _kane_trajectory(q0, qdot0, t1):
    field = kanes_equations()

    def rhs(_, state):
        qdot, udot = field(state[:5], state[5:], _parameters())
        return np.concatenate([qdot, udot])

    solution = scipy.integrate.solve_ivp(
        rhs, (0.0, t1), np.concatenate([q0, qdot0]), method="DOP853", rtol=1e-13, atol=1e-13
    )
    return solution.y[:5, -1], solution.y[5:, -1]


def test_the_same_motion_as_kanes_equations():
    """From a generic start to t = 10: the example's H and A (the index-1 ODE by Dopri8
    at tolerance 1e-13) against Kane's equations (SciPy's DOP853 at 1e-13), positions
    and velocities to 1e-9."""
    q0, p0 = DISK.state(Q0, **RATES)
    system = DISK.canonical
    qdot0 = system.velocity(q0, p0, DISK.args)
    solution = nh.integrate_adaptive(system, (q0, p0), 10.0, DISK.args, rtol=1e-13, atol=1e-13)
    q1, p1 = (leaf[-1] for leaf in solution.ys)
    kane_q, kane_qdot = _kane_trajectory(np.asarray(q0), np.asarray(qdot0), 10.0)
    np.testing.assert_allclose(q1, kane_q, atol=1e-9)
    np.testing.assert_allclose(system.velocity(q1, p1, DISK.args), kane_qdot, atol=1e-9)
    # Not a trivial motion: the disk has turned, leaned and rolled away.
    assert float(jnp.max(jnp.abs(q1 - q0))) > 1.0


@pytest.mark.parametrize(("lean", "turn_rate"), [(0.3, 1.5), (-0.4, 2.0)])
def test_steady_rolling_is_steady_for_kane_and_kept_by_gonzalez_r(lean, turn_rate):
    """The steady state of `steady_rolling` has no acceleration by Kane's equations
    (an independent check of its condition), and GONZALEZ-R keeps it to roundoff:
    the lean constant, the heading turning at exactly the steady rate, the contact
    point on a circle."""
    q0, p0 = DISK.steady_rolling(lean, turn_rate)
    qdot0 = DISK.canonical.velocity(q0, p0, DISK.args)
    _, udot = kanes_equations()(np.asarray(q0), np.asarray(qdot0), _parameters())
    np.testing.assert_allclose(udot[2:], 0.0, atol=1e-14)  # phi, theta, psi
    h, steps = 0.02, 1000
    solution = nh.integrate(DISK.canonical, nh.GonzalezR(), (q0, p0), h, steps, args=DISK.args, save_every=10)
    q = solution.ys[0]
    np.testing.assert_allclose(q[:, 3], lean, atol=1e-12)
    np.testing.assert_allclose(jnp.diff(q[:, 2]), 10 * h * turn_rate, atol=1e-12)
    # The contact point (x, y) runs on a circle: equal chords for equal times.
    chords = jnp.linalg.norm(jnp.diff(q[:, :2], axis=0), axis=1)
    np.testing.assert_allclose(chords, chords[0], atol=1e-12)


def test_gonzalez_r_keeps_energy_and_both_constraints_and_both_forms_agree():
    """GONZALEZ-R from the generic start: energy and both rolling constraints to
    roundoff over 2 000 steps; the Lagrangian form (`from_lagrangian`) gives the same
    trajectory as the mass-matrix Hamiltonian to roundoff."""
    y0 = DISK.state(Q0, **RATES)
    run = eqx.filter_jit(lambda system: nh.integrate(system, nh.GonzalezR(), y0, 0.01, 2000, args=DISK.args, save_every=100))
    by_hamiltonian = run(DISK.canonical)
    energy = by_hamiltonian.energy
    assert float(jnp.max(jnp.abs(energy / energy[0] - 1))) <= 1e-13
    assert float(jnp.max(jnp.abs(by_hamiltonian.constraint))) <= 1e-14
    by_lagrangian = run(DISK.canonical_from_lagrangian)
    np.testing.assert_allclose(by_lagrangian.ys[0], by_hamiltonian.ys[0], atol=1e-11)
    np.testing.assert_allclose(by_lagrangian.ys[1], by_hamiltonian.ys[1], atol=1e-11)


def test_gonzalez_r_converges_to_kanes_motion_at_second_order():
    """GONZALEZ-R's position at t = 2 against Kane's: errors falling like h^2."""
    y0 = DISK.state(Q0, **RATES)
    qdot0 = DISK.canonical.velocity(*y0, DISK.args)
    kane_q, _ = _kane_trajectory(np.asarray(y0[0]), np.asarray(qdot0), 2.0)
    errors = []
    for steps in (50, 100, 200):
        solution = nh.integrate(DISK.canonical, nh.GonzalezR(), y0, 2.0 / steps, steps, args=DISK.args, save_every=steps)
        errors.append(float(jnp.max(jnp.abs(solution.ys[0][-1] - kane_q))))
    orders = np.log2(np.asarray(errors[:-1]) / np.asarray(errors[1:]))
    np.testing.assert_allclose(orders, 2.0, atol=0.15)
