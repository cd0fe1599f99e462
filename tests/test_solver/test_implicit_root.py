"""The derivatives of a step's root (`nhjax._solver.base._implicit_root`) and of its
exchange, in forward and reverse mode, against the implicit function theorem evaluated
independently: du/dtheta = -(dF/du)^{-1} dF/dtheta from Jacobians of F formed by
`jax.jacfwd` and a dense solve. With few data entries the step's linearisation forms its
derivative along the data; with many, it takes one tangent along them; both are checked."""

import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
import pytest

from nhjax._solver.base import _implicit_root, _implicit_root_and_exchange, FORMED_DATA_DERIVATIVE_LIMIT


N = 3
WEIGHTS = jnp.array([[0.9, -0.4, 0.3], [0.2, 0.7, -0.5], [-0.6, 0.1, 0.8]])


def residual(u, data):
    forcing = data["shift"] + data["load"][: u.shape[0]] * jnp.sum(data["load"] ** 2)
    return u - data["step"] * jnp.tanh(WEIGHTS @ u + forcing)


def exchange(u, data):
    return data["step"] * jnp.sum(jnp.sin(u) * data["shift"])


def equations(u, data):
    return residual(u, data), exchange(u, data)


def data_of(theta, load_size):
    return dict(shift=theta[:N], step=theta[N], load=theta[N + 1 : N + 1 + load_size])


def root_of(data):
    """The root by plain fixed-point iteration (a contraction by 0.2 or less per
    iteration), cut from differentiation: its derivatives come from the rule alone."""
    data = jax.tree.map(lax.stop_gradient, data)
    return lax.fori_loop(0, 200, lambda _, u: u - residual(u, data), jnp.zeros(N))


def root(theta, load_size):
    """The root as nhjax's steps return it, its derivatives by `_implicit_root`."""
    data = data_of(theta, load_size)
    return _implicit_root(root_of(data), data, residual=residual)


def parameters(load_size):
    return jnp.concatenate([jnp.array([0.3, -0.2, 0.5, 0.15]), 0.1 * jnp.sin(jnp.arange(load_size) + 1.0)])


def by_the_implicit_function_theorem(theta, load_size):
    """(du/dtheta, dE/dtheta) from Jacobians of F and E in u and in theta."""
    u = root_of(data_of(theta, load_size))
    in_u = jax.jacfwd(residual)(u, data_of(theta, load_size))
    in_theta = jax.jacfwd(lambda t: residual(u, data_of(t, load_size)))(theta)
    root_derivative = -np.linalg.solve(in_u, in_theta)
    exchange_derivative = jax.grad(exchange)(u, data_of(theta, load_size)) @ root_derivative + jax.grad(
        lambda t: exchange(u, data_of(t, load_size))
    )(theta)
    return root_derivative, exchange_derivative


@pytest.mark.parametrize("load_size", [N, FORMED_DATA_DERIVATIVE_LIMIT + 8], ids=["data formed", "data tangent"])
def test_root_and_exchange_derivatives_follow_the_implicit_function_theorem(load_size):
    theta = parameters(load_size)

    def root_and_exchange(theta):
        data = data_of(theta, load_size)
        return _implicit_root_and_exchange(root_of(data), data, residual=residual, equations=equations)

    expected_root, expected_exchange = by_the_implicit_function_theorem(theta, load_size)
    assert float(jnp.max(jnp.abs(expected_root))) > 0.01  # the root moves with the data
    for transform in (jax.jacfwd, jax.jacrev):
        root_derivative = jax.jit(transform(root), static_argnums=1)(theta, load_size)
        np.testing.assert_allclose(root_derivative, expected_root, rtol=1e-12, atol=1e-14)
        root_derivative, exchange_derivative = jax.jit(transform(root_and_exchange))(theta)
        np.testing.assert_allclose(root_derivative, expected_root, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(exchange_derivative, expected_exchange, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("load_size", [N, FORMED_DATA_DERIVATIVE_LIMIT + 8], ids=["data formed", "data tangent"])
def test_second_derivatives_of_the_root_match_differences_of_the_first(load_size):
    """Forward over forward and reverse over forward (the second derivatives nhjax
    supports, `nhjax.integrate`), against central differences of the first derivative
    from the implicit function theorem."""
    theta = parameters(load_size)
    step = 1e-5
    differences = np.stack(
        [
            (
                by_the_implicit_function_theorem(theta.at[i].add(step), load_size)[0]
                - by_the_implicit_function_theorem(theta.at[i].add(-step), load_size)[0]
            )
            / (2 * step)
            for i in range(theta.shape[0])
        ],
        axis=-1,
    )
    assert float(np.max(np.abs(differences))) > 0.01
    for second in (jax.jacfwd(jax.jacfwd(root)), jax.jacrev(jax.jacfwd(root))):
        second_derivative = jax.jit(second, static_argnums=1)(theta, load_size)
        np.testing.assert_allclose(second_derivative, differences, rtol=1e-6, atol=1e-8)
