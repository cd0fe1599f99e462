"""GONZALEZ-F (simpDirect): energy to roundoff, the constraint only to O(h^2)."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import nhjax as nh

from ..helpers import (
    final_state_errors,
    fitted_order,
    reference_final_state,
    relative_energy_error,
    step_there_and_back,
)


GEARBOX = nh.examples.gearbox()
QUARTIC = nh.examples.chaotic_quartic()
METHOD = nh.GonzalezF()
STEP_SIZES = (0.2, 0.1, 0.05)


def test_energy_to_roundoff_while_the_constraint_drifts_visibly():
    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    solution = nh.integrate(GEARBOX.canonical, METHOD, y0, 0.1, 10_000, save_every=100)
    assert solution.result == nh.RESULTS.successful
    assert relative_energy_error(solution) <= 1e-13
    assert float(jnp.max(jnp.abs(solution.constraint))) >= 1e-4


def test_second_order_in_the_state_and_in_the_constraint():
    y0 = GEARBOX.random_initial_state(jax.random.key(1))
    t1 = 5.0
    reference = reference_final_state(GEARBOX.canonical, y0, t1)
    errors = final_state_errors(GEARBOX.canonical, METHOD, y0, t1, STEP_SIZES, reference)
    assert 1.9 <= fitted_order(STEP_SIZES, errors) <= 2.1, errors
    violations = [
        float(jnp.max(jnp.abs(nh.integrate(GEARBOX.canonical, METHOD, y0, h, round(t1 / h)).constraint)))
        for h in STEP_SIZES
    ]
    assert 1.8 <= fitted_order(STEP_SIZES, violations) <= 2.2, violations


def test_time_symmetric():
    """A step with h, then one with -h, returns to the start."""
    y0 = QUARTIC.from_adapted(QUARTIC.initial_state(0.9))
    back, results = step_there_and_back(QUARTIC.canonical, METHOD, y0, 0.2)
    assert all(result == diffrax.RESULTS.successful for result in results)
    np.testing.assert_allclose(back[0], y0[0], atol=1e-14)
    np.testing.assert_allclose(back[1], y0[1], atol=1e-14)


def test_every_trajectory_of_a_batch_of_200_converges():
    """200 random gearbox states, 500 steps, vmapped: every root find converges, the
    pendulum spinning far from the origin included. (With the constraint equation scaled
    by h / max(1 + |q|) one of these failed near step 497: that scaling lifted the
    rounding floor of the impulse's correction towards the tolerance.)"""
    states = jax.vmap(GEARBOX.random_initial_state)(jax.random.split(jax.random.key(1), 200))
    run = jax.vmap(lambda y0: nh.integrate(GEARBOX.canonical, METHOD, y0, 0.1, 500, save_every=500, throw=False))
    solution = jax.jit(run)(states)
    assert bool(jnp.all(solution.result == nh.RESULTS.successful))
    assert float(jnp.max(jnp.abs(solution.ys[0][:, -1, 2]))) > 30  # some pendulums spin


def test_long_vmapped_runs_do_not_fail_at_the_rounding_floor():
    """Ten gearbox states, 2000 steps, vmapped. One of them (its pendulum wound to
    q3 = -170 to -260) used to stop near step 1856 with a root find at its 20-iteration
    limit: the iterates circled the root at about one tolerance, the residual's rounding
    floor (see `nhjax._solver.chord.Chord`), and whether the plain test passed depended
    on the program's rounding."""
    states = jax.vmap(GEARBOX.random_initial_state)(jax.random.split(jax.random.key(1), 10))
    run = jax.vmap(lambda y0: nh.integrate(GEARBOX.canonical, METHOD, y0, 0.1, 2000, save_every=2000, throw=False))
    solution = jax.jit(run)(states)
    assert bool(jnp.all(solution.result == nh.RESULTS.successful)), solution.stats
    assert int(jnp.max(solution.stats["max_root_find_steps"])) <= 12, solution.stats
    assert float(jnp.max(jnp.abs(solution.energy / solution.energy[:, :1] - 1))) <= 1e-12
