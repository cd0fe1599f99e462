"""The rolling disk (§2): the method is the implicit midpoint rule and keeps the
discrete constraints exactly."""

import jax
import jax.numpy as jnp
import numpy as np

import nhjax as nh


DISK = nh.examples.rolling_disk()


def test_discrete_constraints_to_roundoff():
    """(x1' - x1) - r (phi' - phi) cos(theta_mid) = 0 and likewise for x2."""
    x0 = DISK.initial_state(rho1=1.3, rho2=0.9)
    solution = nh.integrate(DISK.adapted, nh.DiscreteGradient(), x0, 0.3, 1000, args=DISK.args)
    q = solution.ys[:, :4]
    residual = nh.examples.discrete_constraint_residual(DISK.constraints, q, DISK.args)
    assert float(jnp.max(jnp.abs(residual))) <= 1e-14 * float(jnp.max(jnp.abs(q)))


def test_momenta_are_constant_and_angles_exact():
    """theta and phi advance exactly linearly (the discrete gradient of a quadratic H is
    the midpoint gradient), as the exact solution does."""
    x0 = DISK.initial_state(rho1=1.3, rho2=0.9)
    solution = nh.integrate(DISK.adapted, nh.DiscreteGradient(), x0, 0.3, 100, args=DISK.args)
    exact = jax.vmap(lambda t: DISK.exact_solution(t, x0))(solution.ts)
    np.testing.assert_allclose(solution.ys[:, 2:], exact[:, 2:], rtol=1e-13, atol=1e-13)


def test_adapted_coordinates_round_trip():
    x = DISK.initial_state(theta=0.4, rho1=1.3, rho2=0.9)
    q, p = DISK.from_adapted(x)
    velocity = jnp.linalg.solve(DISK.metric(q, DISK.args), p)
    assert float(jnp.max(jnp.abs(DISK.constraints(q, DISK.args) @ velocity))) <= 1e-15
    np.testing.assert_allclose(DISK.to_adapted(q, p), x, atol=1e-15)
