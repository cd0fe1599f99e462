"""GONZALEZ-F (simpDirect): the constraint only to O(h^2), and batches that converge.
(Order, energy to roundoff and symmetry: test_methods.py.)"""

import jax
import jax.numpy as jnp

import nhjax as nh

from ..helpers import fitted_order, runs_at_step_sizes


GEARBOX = nh.examples.gearbox()
METHOD = nh.GonzalezF()
STEP_SIZES = (0.2, 0.1, 0.05)


def test_the_constraint_violation_is_second_order():
    """The constraint on the discrete-gradient velocity leaves A(q) dH/dp at step ends
    at the method's error, O(h^2): its maximum over t in [0, 5], from one compiled run
    per step size (vmapped over dt)."""
    y0 = GEARBOX.random_initial_state(jax.random.key(1))
    runs = runs_at_step_sizes(GEARBOX.canonical, METHOD, y0, STEP_SIZES, 100, GEARBOX.args)
    assert bool(jnp.all(runs.result == nh.RESULTS.successful))
    violations = [
        float(jnp.max(jnp.abs(runs.constraint[index, : round(5.0 / h) + 1])))
        for index, h in enumerate(STEP_SIZES)
    ]
    assert 1.8 <= fitted_order(STEP_SIZES, violations) <= 2.2, violations


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
    floor (see `nhjax._solver.chord.PresetChord`), and whether the plain test passed depended
    on the program's rounding."""
    states = jax.vmap(GEARBOX.random_initial_state)(jax.random.split(jax.random.key(1), 10))
    run = jax.vmap(lambda y0: nh.integrate(GEARBOX.canonical, METHOD, y0, 0.1, 2000, save_every=2000, throw=False))
    solution = jax.jit(run)(states)
    assert bool(jnp.all(solution.result == nh.RESULTS.successful)), solution.stats
    assert int(jnp.max(solution.stats["max_root_find_steps"])) <= 12, solution.stats
    assert float(jnp.max(jnp.abs(solution.energy / solution.energy[:, :1] - 1))) <= 1e-12
