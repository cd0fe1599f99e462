"""I-DLA (midpoint discrete Lagrangian, constraint force split evenly): the discrete
Lagrange-d'Alembert equations from an independent L_d, an energy error that is a
random walk, float32. (Order, the constraint to roundoff and symmetry:
test_methods.py.)"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh

from ..helpers import canonical_starts, check_float32, energy_variance_slopes, first_step


QUARTIC = nh.examples.chaotic_quartic()
METHOD = nh.IDLA()
STEP_SIZE = 0.2
STARTS = canonical_starts()


@pytest.mark.parametrize("name", ["quartic, n = 7", "sleigh, q-dependent M"])
def test_a_step_solves_the_discrete_lagrange_dalembert_equations(name):
    """From L(q, v) = 1/2 v^T M(q) v - V(q) (M from `metric`, V = H(q, 0)) and
    L_d = h L((q0 + q1)/2, (q1 - q0)/h) by autodiff, independently of the method's
    momentum form: p0 + D1 L_d = -(h/2) A(qbar)^T lambda and
    p1 - D2 L_d = +(h/2) A(qbar)^T lambda for one lambda, and A(q1) dH/dp(q1, p1) = 0."""
    example, y0 = STARTS[name]
    system, args, h = example.canonical, example.args, STEP_SIZE
    (q0, p0), (q1, p1) = y0, first_step(example, METHOD, y0, h)

    def lagrangian(q, v):
        return 0.5 * v @ system.metric(q, args) @ v - system.hamiltonian(q, jnp.zeros_like(q), args)

    def discrete_lagrangian(a, b):
        return h * lagrangian(0.5 * (a + b), (b - a) / h)

    @jax.jit
    def transforms(q0, p0, q1, p1):
        before = p0 + jax.grad(discrete_lagrangian, argnums=0)(q0, q1)
        after = p1 - jax.grad(discrete_lagrangian, argnums=1)(q0, q1)
        return before, after

    before, after = transforms(q0, p0, q1, p1)
    a_mid = system.constraints(0.5 * (q0 + q1), args)
    multiplier, *_ = jnp.linalg.lstsq(0.5 * h * a_mid.T, after)
    assert float(jnp.max(jnp.abs(after))) > 1e-3  # the constraint force is at work
    # The difference quotient (q1 - q0)/h in D L_d turns the rounding of q into 1e-16/h.
    np.testing.assert_allclose(after, 0.5 * h * a_mid.T @ multiplier, rtol=0, atol=1e-14)
    np.testing.assert_allclose(before, -0.5 * h * a_mid.T @ multiplier, rtol=0, atol=1e-14)
    velocity = jax.grad(system.hamiltonian, argnums=1)(q1, p1, args)
    assert float(jnp.max(jnp.abs(system.constraints(q1, args) @ velocity))) <= 1e-15


def test_energy_error_is_a_random_walk_on_the_chaotic_quartic():
    """Over 100 random states with H = 3.06 the variance of H(t) - H(0) grows linearly
    in t (fitted with an intercept over [T/10, T], as for SI-DLA), with a slope that
    scales like h^4: slope / h^4 agrees at h = 0.2 and 0.1 within a factor 2, and is of
    the order of SI-DLA's 1e-4 or up to two orders above it (about 1.3e-3 here: on this
    system the midpoint discrete Lagrangian's energy error is larger than the
    Stormer-Verlet-like SI-DLA's)."""
    states = jax.vmap(QUARTIC.from_adapted)(QUARTIC.random_initial_states(jax.random.key(0), 100))
    scaled_slopes = [slope / h**4 for h, slope in energy_variance_slopes(QUARTIC.canonical, METHOD, states)]
    assert all(1e-4 <= slope <= 1e-2 for slope in scaled_slopes), scaled_slopes
    assert 0.5 <= scaled_slopes[0] / scaled_slopes[1] <= 2, scaled_slopes


def test_float32():
    check_float32(METHOD, *STARTS["gearbox, M = I"])