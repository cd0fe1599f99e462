"""The gearbox (§4.4) with H = |p|^2/2 + V: its separate invariants, along the exact flow."""

import jax
import jax.numpy as jnp
import numpy as np

import nhjax as nh


GEARBOX = nh.examples.gearbox()


def test_random_initial_states_are_generic_and_on_the_constraint():
    states = [GEARBOX.random_initial_state(jax.random.key(seed)) for seed in range(5)]
    for q, p in states:
        np.testing.assert_allclose(GEARBOX.canonical.constraint_residual((q, p), None), 0.0, atol=1e-16)
    assert len({float(q[0]) for q, _ in states}) == 5


def test_exact_flow_conserves_the_pendulum_and_the_oscillator_energies_separately():
    """Along a tight Dopri8 solution of the index-1 equations, H3 and H - H3 are each
    constant, and the oscillators stay bounded (they would not with the printed -V)."""
    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    solution = nh.integrate_adaptive(GEARBOX.canonical, y0, 50.0, save_at=jnp.linspace(0.0, 50.0, 101))
    qs, ps = solution.ys
    pendulum = GEARBOX.pendulum_energy(qs, ps)
    total = jax.vmap(lambda q, p: GEARBOX.canonical.energy((q, p), None))(qs, ps)
    np.testing.assert_allclose(pendulum, pendulum[0], atol=1e-10)
    np.testing.assert_allclose(total - pendulum, total[0] - pendulum[0], atol=1e-10)
    assert float(jnp.max(jnp.abs(qs[:, :2]))) <= float(jnp.sqrt(2 * (total[0] - pendulum[0]))) + 1e-10
