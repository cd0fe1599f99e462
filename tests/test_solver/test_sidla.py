"""SI-DLA (McLachlan & Perlmutter eq. 4.18): the printed equations, an energy error that
is a random walk, the constant-metric path, float32. (Order, the constraint to
roundoff and symmetry: test_methods.py.)"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh

from ..helpers import canonical_starts, check_float32, energy_variance_slopes, first_step, runs_at_step_sizes


QUARTIC = nh.examples.chaotic_quartic()
METHOD = nh.SIDLA()
GENERAL = nh.SIDLA(constant_metric=False)
STEP_SIZE = 0.2
STARTS = canonical_starts()


def test_constant_metric_is_detected_from_the_program():
    """M = I for the gearbox and the quartic: k = 1 unknown. The sleigh's metric depends
    on theta: 2n + k = 7 unknowns."""

    def unknowns(method, example, y0):
        system, args = example.canonical, example.args

        def guess(y0):
            return method.setup(system, 0.0, 0.1, y0, args, method.initial_carry(system, y0, args))[0]

        return jax.eval_shape(guess, y0).shape

    for name, expected in [("gearbox, M = I", 1), ("quartic, n = 7", 1), ("sleigh, q-dependent M", 7)]:
        example, y0 = STARTS[name]
        assert METHOD.metric_is_constant(example.canonical, y0, example.args) == (expected == 1)
        assert unknowns(METHOD, example, y0) == (expected,)
    assert unknowns(GENERAL, *STARTS["gearbox, M = I"]) == (7,)


def test_detection_follows_calls_and_args():
    """A metric held in `args` is constant; one built from q inside a jitted helper is
    not; a potential inside a jitted helper does not make the metric q-dependent."""

    @jax.jit
    def potential(q):
        return 0.5 * q @ q

    @jax.jit
    def kinetic(q, p):
        return 0.5 * p @ p / (2.0 + jnp.cos(q[0]))

    def constraints(q, args):
        return jnp.array([[1.0, q[0], 0.0]])

    q = jnp.array([0.1, 0.2, 0.3])
    p = jnp.array([0.2, -0.1, 0.4])
    from_args = nh.NonholonomicSystem(lambda q, p, m: 0.5 * p @ m @ p + potential(q), constraints)
    from_q = nh.NonholonomicSystem(lambda q, p, args: kinetic(q, p) + potential(q), constraints)
    assert METHOD.metric_is_constant(from_args, (q, p), 2.0 * jnp.eye(3))
    assert not METHOD.metric_is_constant(from_q, (q, p), None)


@pytest.mark.parametrize("name", ["gearbox, M = I", "quartic, n = 7"])
def test_constant_metric_path_equals_the_general_path(name):
    """The same method either way: equal to roundoff over the first 100 steps (later the
    quartic's chaos amplifies the rounding differences)."""
    example, y0 = STARTS[name]
    fast, general = (runs_at_step_sizes(example.canonical, method, y0, (0.2, 0.1, 0.05), 100, example.args) for method in (METHOD, GENERAL))
    assert bool(jnp.all(fast.result == nh.RESULTS.successful))
    assert bool(jnp.all(general.result == nh.RESULTS.successful))
    for fast_leaf, general_leaf in zip(fast.ys, general.ys):
        np.testing.assert_allclose(fast_leaf[:, :101], general_leaf[:, :101], rtol=0, atol=1e-13)


@pytest.mark.parametrize("name", ["gearbox, M = I", "sleigh, q-dependent M"])
def test_a_step_solves_the_printed_equations(name):
    """eq. (4.18) checked with autodiff of H directly: q1/2, the q equation with the
    velocity at (q1, p1), the momentum equation up to a force in the range of
    A(q1/2)^T, and the constraint at the end."""
    example, y0 = STARTS[name]
    system, args, h = example.canonical, example.args, STEP_SIZE
    (q0, p0), (q1, p1) = y0, first_step(example, METHOD, y0, h)
    dh_dq = jax.grad(system.hamiltonian, argnums=0)
    dh_dp = jax.grad(system.hamiltonian, argnums=1)
    q_half = q0 + 0.5 * h * dh_dp(q0, p0, args)
    np.testing.assert_allclose(q1, q_half + 0.5 * h * dh_dp(q1, p1, args), rtol=0, atol=1e-14)
    force = p1 - p0 + 0.5 * h * (dh_dq(q_half, p0, args) + dh_dq(q_half, p1, args))
    a_half = system.constraints(q_half, args)
    multiplier, *_ = jnp.linalg.lstsq(h * a_half.T, force)
    np.testing.assert_allclose(force, h * a_half.T @ multiplier, rtol=0, atol=1e-14)
    assert float(jnp.max(jnp.abs(force))) > 1e-3  # the constraint force is at work
    assert float(jnp.max(jnp.abs(system.constraints(q1, args) @ dh_dp(q1, p1, args)))) <= 1e-15


def test_energy_error_is_a_random_walk_on_the_chaotic_quartic():
    """McLachlan & Perlmutter (and Figure 1): over random states with H = 3.06 the
    variance of H(t) - H(0) grows like 1e-4 h^4 t. The variance also holds a bounded
    part (about 0.1 h^4, the energy's oscillation along a trajectory), which dominates
    below t ~ 1000, so the slope is fitted with an intercept over [T/10, T] with
    T = 2 10^4 h. At h = 0.2 and 0.1 (a factor 16 in h^4) the slope / h^4 must be within
    a factor 5 of 1e-4."""
    states = jax.vmap(QUARTIC.from_adapted)(QUARTIC.random_initial_states(jax.random.key(0), 100))
    energies = jax.vmap(QUARTIC.canonical.energy, (0, None))(states, None)
    np.testing.assert_allclose(energies, 3.06, rtol=1e-14)
    for h, slope in energy_variance_slopes(QUARTIC.canonical, METHOD, states):
        assert 2e-5 <= slope / h**4 <= 5e-4, (h, slope / h**4)


def test_float32():
    check_float32(METHOD, *STARTS["gearbox, M = I"])


def test_invalid_option():
    with pytest.raises(ValueError, match="constant_metric"):
        nh.SIDLA(constant_metric="yes")
