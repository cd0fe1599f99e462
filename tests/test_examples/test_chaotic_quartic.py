"""The chaotic quartic (§4.1): the paper's initial states, the constraint, the structure."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh


QUARTIC = nh.examples.chaotic_quartic()


def test_random_initial_states_have_the_papers_energy_and_satisfy_the_constraint():
    states = QUARTIC.random_initial_states(jax.random.key(0), 50)
    energies = jax.vmap(QUARTIC.adapted.energy, in_axes=(0, None))(states, None)
    np.testing.assert_allclose(energies, 3.06, rtol=1e-14)
    q, p = jax.vmap(QUARTIC.from_adapted)(states)
    residual = jax.vmap(lambda q, p: QUARTIC.constraints(q) @ p)(q, p)
    assert float(jnp.max(jnp.abs(residual))) <= 1e-15
    assert float(jnp.std(states[:, 0])) > 0.1  # the angle really varies


def test_discrete_constraint_and_canonical_constraint_to_roundoff():
    x0 = QUARTIC.initial_state(0.9)
    solution = nh.integrate(QUARTIC.adapted, nh.DiscreteGradient(), x0, 0.1, 1000)
    discrete = nh.examples.discrete_constraint_residual(QUARTIC.constraints, solution.ys[:, :7])
    assert float(jnp.max(jnp.abs(discrete))) <= 1e-14
    qs, ps = jax.vmap(QUARTIC.from_adapted)(solution.ys)
    canonical = jax.vmap(lambda q, p: QUARTIC.constraints(q) @ p)(qs, ps)
    assert float(jnp.max(jnp.abs(canonical))) <= 1e-14


def test_structure_is_the_printed_fcseq_and_skew():
    """(fcseq) from (PiMat): frame columns X_i = d/dw_i, X_{n+i} = w_i d/dx - d/dz_i,
    and the bracket block -kappa I / kappa I."""
    x = QUARTIC.initial_state(0.3).at[7:].set(jnp.array([0.1, -0.2, 0.3, 0.4, 0.5, -0.6]))
    structure = QUARTIC.adapted.structure(x, None)
    np.testing.assert_array_equal(structure, -structure.T)
    w, eta = x[1:4], x[10:13]
    kappa = (w @ eta) / (1 + w @ w)
    np.testing.assert_allclose(structure[0, 10:13], w)
    np.testing.assert_allclose(structure[1:4, 7:10], jnp.eye(3))
    np.testing.assert_allclose(structure[4:7, 10:13], -jnp.eye(3))
    np.testing.assert_allclose(structure[7:10, 10:13], -kappa * jnp.eye(3))


@pytest.mark.parametrize("n", [1, 2, 5])
def test_other_sizes(n):
    quartic = nh.examples.chaotic_quartic(n)
    x0 = jnp.linspace(-0.5, 0.5, 4 * n + 1)
    solution = nh.integrate(quartic.adapted, nh.DiscreteGradient(), x0, 0.1, 100)
    assert float(jnp.max(jnp.abs(solution.energy / solution.energy[0] - 1))) <= 1e-13


def test_bad_sizes_are_rejected():
    with pytest.raises(ValueError, match="n >= 1"):
        nh.examples.chaotic_quartic(0)
    with pytest.raises(ValueError, match="n = 3"):
        nh.examples.chaotic_quartic(2).initial_state(0.1)
    with pytest.raises(ValueError, match="4n \\+ 1"):
        nh.integrate(QUARTIC.adapted, nh.DiscreteGradient(), jnp.zeros(6), 0.1, 10)
