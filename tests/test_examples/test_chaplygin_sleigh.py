"""Proposition 4.1 and the discrete constraint on the Chaplygin sleigh (§4.2)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh


SLEIGH = nh.examples.chaplygin_sleigh(J=8.0, a=1.0, m=1.0)


@pytest.mark.parametrize("rho1", [-0.001, 0.001])
def test_leaves_the_unstable_equilibrium_for_the_stable_one(rho1):
    """Figure 2's setting: h = 0.5, rho2 = -0.6. The discrete rho settles at rho1 = 0,
    rho2 = +sqrt(rho1^2 + rho2^2), with rho1 keeping its sign (rho1 = 0 is invariant)."""
    x0 = SLEIGH.initial_state(rho1=rho1)
    solution = nh.integrate(SLEIGH.adapted, nh.DiscreteGradient(), x0, 0.5, 1000, args=SLEIGH.args)
    rho = solution.ys[:, 3:]
    radius = float(jnp.hypot(rho1, -0.6))
    assert abs(float(rho[-1, 0])) < 1e-6
    assert abs(float(rho[-1, 1]) - radius) < 1e-12
    assert bool(jnp.all(jnp.sign(rho[:, 0]) == np.sign(rho1)))
    assert float(jnp.max(jnp.abs(rho[:, 1]))) <= radius * (1 + 1e-14)


@pytest.mark.parametrize("rho2", [-0.6, 0.6, 2.0])
def test_linearisation_at_equilibria_matches_proposition(rho2):
    """The one-step map linearised at (0, rho2) has eigenvalues 1 and
    (2 - h C rho2)/(2 + h C rho2): below 1 (stable) for rho2 > 0, above 1 for rho2 < 0."""
    h, args = 0.5, SLEIGH.args
    method, system = nh.DiscreteGradient(), SLEIGH.adapted

    def step(rho):
        x = jnp.concatenate([jnp.array([-5.0, 0.0, 0.1]), rho])
        state = method.init(system, 0.0, h, x, args)
        return method.step(system, 0.0, h, x, args, state, False)[0][3:]

    jacobian = jax.jacfwd(step)(jnp.array([0.0, rho2]))
    c = float(SLEIGH.bracket_coefficient(args))
    expected = (2 - h * c * rho2) / (2 + h * c * rho2)
    np.testing.assert_allclose(jacobian, np.diag([expected, 1.0]), atol=1e-12)
    assert (expected < 1) == (rho2 > 0)


def test_discrete_constraint_to_roundoff():
    """q' - q = h X(qbar) dH: A(qbar)(q' - q) = 0 with qbar the midpoint."""
    x0 = SLEIGH.initial_state(rho1=0.4, rho2=-0.3)
    solution = nh.integrate(SLEIGH.adapted, nh.DiscreteGradient(), x0, 0.5, 500, args=SLEIGH.args)
    residual = nh.examples.discrete_constraint_residual(SLEIGH.constraints, solution.ys[:, :3], SLEIGH.args)
    assert float(jnp.max(jnp.abs(residual))) <= 1e-14


def test_adapted_coordinates_round_trip_onto_the_constraint():
    x = SLEIGH.initial_state(rho1=0.4, rho2=-0.3)
    q, p = SLEIGH.from_adapted(x)
    velocity = jnp.linalg.solve(SLEIGH.metric(q, SLEIGH.args), p)
    assert float(jnp.max(jnp.abs(SLEIGH.constraints(q, SLEIGH.args) @ velocity))) <= 1e-15
    np.testing.assert_allclose(SLEIGH.to_adapted(q, p), x, atol=1e-15)
    # the orthonormal frame makes H = |rho|^2 / 2 equal the kinetic energy p M^-1 p / 2
    np.testing.assert_allclose(0.5 * p @ velocity, SLEIGH.adapted.energy(x, SLEIGH.args), rtol=1e-14)
