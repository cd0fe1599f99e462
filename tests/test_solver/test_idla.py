"""I-DLA (midpoint discrete Lagrangian): the discrete Lagrange-d'Alembert equations of
both forms from an independent L_d, an energy error that is a random walk on
McLachlan & Perlmutter's line, the midpoint form's order and symmetry, float32.
(The default's order, constraint to roundoff and symmetry: test_methods.py.)"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh

from ..helpers import (
    canonical_starts,
    check_float32,
    energy_variance_slopes,
    final_state_errors,
    first_step,
    fitted_order,
    reference_final_state,
    step_there_and_back,
)


QUARTIC = nh.examples.chaotic_quartic()
METHOD = nh.IDLA()
MIDPOINT = nh.IDLA(constraint_force="midpoint")
STEP_SIZE = 0.2
STARTS = canonical_starts()
LAGRANGE_DALEMBERT_STARTS = ["quartic, n = 7", "sleigh, q-dependent M", "disk, k = 2"]


def _discrete_lagrangian_derivatives(example, h):
    """D_1 L_d and D_2 L_d by autodiff of L_d = h L((a + b)/2, (b - a)/h), with
    L(q, v) = 1/2 v^T M(q) v - V(q) (M from `metric`, V = H(q, 0)): independent of the
    method's momentum form."""
    system, args = example.canonical, example.args

    def lagrangian(q, v):
        return 0.5 * v @ system.metric(q, args) @ v - system.hamiltonian(q, jnp.zeros_like(q), args)

    def discrete_lagrangian(a, b):
        return h * lagrangian(0.5 * (a + b), (b - a) / h)

    return jax.jit(jax.grad(discrete_lagrangian, argnums=0)), jax.jit(jax.grad(discrete_lagrangian, argnums=1))


def _outside_range(a, vector):
    """The part of `vector` outside the range of a^T (least squares), and the coefficient."""
    coefficient, *_ = jnp.linalg.lstsq(a.T, vector)
    return vector - a.T @ coefficient, coefficient


def _velocity_constraint(example, q, p):
    system, args = example.canonical, example.args
    return system.constraints(q, args) @ jax.grad(system.hamiltonian, argnums=1)(q, p, args)


@pytest.mark.parametrize("name", LAGRANGE_DALEMBERT_STARTS)
def test_two_steps_solve_the_discrete_lagrange_dalembert_equations(name):
    """The default form, over two steps (q0, q1, q2): the DLA equation at the node q1,
    D_2 L_d(q0, q1) + D_1 L_d(q1, q2) in the range of A(q1)^T, and not zero (the
    constraint force is at work); the discrete constraint A((q_k + q_k+1)/2)(q_k+1 - q_k)
    = 0 on both steps; and each node's momentum on D* and between the two discrete
    Legendre transforms: p_k - D_2 L_d and p_k + D_1 L_d in the range of A(q_k)^T."""
    example, y0 = STARTS[name]
    system, args, h = example.canonical, example.args, STEP_SIZE
    d1, d2 = _discrete_lagrangian_derivatives(example, h)
    solution = nh.integrate(system, METHOD, y0, h, 2, args=args)
    qs, ps = solution.ys
    # The difference quotient (q1 - q0)/h in D L_d turns the rounding of q into 1e-16/h.
    atol = 1e-14
    node, force = _outside_range(system.constraints(qs[1], args), d2(qs[0], qs[1]) + d1(qs[1], qs[2]))
    assert float(jnp.max(jnp.abs(force))) > 1e-3
    np.testing.assert_allclose(node, 0, atol=atol)
    for k in range(2):
        middle = system.constraints(0.5 * (qs[k] + qs[k + 1]), args)
        np.testing.assert_allclose(middle @ (qs[k + 1] - qs[k]), 0, atol=1e-15)
        a = system.constraints(qs[k], args)
        np.testing.assert_allclose(_outside_range(a, ps[k] + d1(qs[k], qs[k + 1]))[0], 0, atol=atol)
        if k > 0:
            np.testing.assert_allclose(_outside_range(a, ps[k] - d2(qs[k - 1], qs[k]))[0], 0, atol=atol)
        assert float(jnp.max(jnp.abs(_velocity_constraint(example, qs[k], ps[k])))) <= 1e-15


@pytest.mark.parametrize("name", LAGRANGE_DALEMBERT_STARTS[:2])
def test_the_midpoint_form_solves_its_equations(name):
    """The midpoint form: p0 + D_1 L_d = -(h/2) A(qbar)^T lambda and
    p1 - D_2 L_d = +(h/2) A(qbar)^T lambda for one lambda, and A(q1) dH/dp(q1, p1) = 0."""
    example, y0 = STARTS[name]
    system, args, h = example.canonical, example.args, STEP_SIZE
    d1, d2 = _discrete_lagrangian_derivatives(example, h)
    (q0, p0), (q1, p1) = y0, first_step(example, MIDPOINT, y0, h)
    before, after = p0 + d1(q0, q1), p1 - d2(q0, q1)
    a_mid = system.constraints(0.5 * (q0 + q1), args)
    multiplier, *_ = jnp.linalg.lstsq(0.5 * h * a_mid.T, after)
    assert float(jnp.max(jnp.abs(after))) > 1e-3
    np.testing.assert_allclose(after, 0.5 * h * a_mid.T @ multiplier, rtol=0, atol=1e-14)
    np.testing.assert_allclose(before, -0.5 * h * a_mid.T @ multiplier, rtol=0, atol=1e-14)
    assert float(jnp.max(jnp.abs(_velocity_constraint(example, q1, p1)))) <= 1e-15


def test_the_midpoint_form_is_second_order_and_symmetric():
    """Against the index-1 reference at t = 2 on the sleigh (q-dependent metric), and a
    step with h then -h returns to the start."""
    example, y0 = STARTS["sleigh, q-dependent M"]
    system, args = example.canonical, example.args
    sizes = (0.1, 0.05, 0.025)
    reference = reference_final_state(system, y0, 2.0, args)
    errors = final_state_errors(system, MIDPOINT, y0, 2.0, sizes, reference, args)
    assert 1.8 <= fitted_order(sizes, errors) <= 2.2, errors
    back, codes = eqx.filter_jit(step_there_and_back)(system, MIDPOINT, y0, STEP_SIZE, args)
    assert all(code == diffrax.RESULTS.successful for code in codes)
    for a, b in zip(back, y0):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-14)


def test_energy_error_is_a_random_walk_on_mclachlan_and_perlmutters_line():
    """Over 100 random states with H = 3.06 the variance of H(t) - H(0) grows linearly
    in t with slope / h^4 within a factor 5 of SI-DLA's 1e-4 at h = 0.2 and 0.1, as the
    paper reports for I-DLA (fitted as for SI-DLA). The midpoint form's slope is about
    1.3e-3 here, outside."""
    states = jax.vmap(QUARTIC.from_adapted)(QUARTIC.random_initial_states(jax.random.key(0), 100))
    scaled_slopes = [slope / h**4 for h, slope in energy_variance_slopes(QUARTIC.canonical, METHOD, states)]
    assert all(2e-5 <= slope <= 5e-4 for slope in scaled_slopes), scaled_slopes


def test_float32():
    check_float32(METHOD, *STARTS["gearbox, M = I"])


def test_invalid_option():
    with pytest.raises(ValueError, match="constraint_force"):
        nh.IDLA(constraint_force="nodes")
