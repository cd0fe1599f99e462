"""The Suslov problem (§4.3): exact solution, order 2, equilibria."""

import jax.numpy as jnp
import numpy as np

import nhjax as nh

from ..helpers import final_state_errors, fitted_order


SUSLOV = nh.examples.suslov()


def test_second_order_against_the_exact_solution():
    rho0 = SUSLOV.initial_state(omega1=1.0, omega2=0.5)
    exact = SUSLOV.exact_solution(10.0, rho0)
    step_sizes = [0.2, 0.1, 0.05]
    errors = final_state_errors(
        SUSLOV.adapted, nh.DiscreteGradient(), rho0, 10.0, step_sizes, exact, args=SUSLOV.args
    )
    assert 1.95 <= fitted_order(step_sizes, errors) <= 2.05


def test_equilibria_are_fixed_and_attract():
    """States with I13 w1 + I23 w2 = 0 do not move; others approach that line."""
    args = SUSLOV.args
    on_line = SUSLOV.initial_state(omega1=args["I23"], omega2=-args["I13"])
    solution = nh.integrate(SUSLOV.adapted, nh.DiscreteGradient(), on_line, 0.1, 100, args=args)
    np.testing.assert_allclose(solution.ys[-1], on_line, rtol=1e-14)
    moving = nh.integrate(SUSLOV.adapted, nh.DiscreteGradient(), SUSLOV.initial_state(), 0.1, 2000, args=args)
    omega = moving.ys[-1] / jnp.array([args["I11"], args["I22"]])
    assert abs(float(args["I13"] * omega[0] + args["I23"] * omega[1])) < 1e-8
