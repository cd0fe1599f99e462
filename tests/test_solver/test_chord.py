"""The chord root finder: convergence, divergence, and stalls at the rounding floor."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from nhjax._solver.chord import chord_inverse, PresetChord, STALL_FACTOR


ATOL = 1e-10
ROOT = jnp.array([0.3, -1.2, 2.0])


def _solve(fn, inverse, max_steps=30):
    return optx.root_find(
        fn, PresetChord(atol=ATOL), jnp.zeros(3), options={"inverse": inverse}, max_steps=max_steps, throw=False
    )


def _floor_residual(amplitude):
    """u - ROOT plus an error of size `amplitude` whose sign follows the side of the root:
    the chord iterates then circle the root in a 2-cycle, as they do when a residual's
    rounding error is of the size of the tolerance."""
    return lambda u, args: u - ROOT + amplitude * jnp.where(u > ROOT, 1.0, -1.0)


def test_contracting_iteration_converges_to_tolerance():
    solution = _solve(lambda u, args: u - ROOT + 0.05 * jnp.sin(u - ROOT), jnp.eye(3))
    assert solution.result == optx.RESULTS.successful
    np.testing.assert_allclose(solution.value, ROOT, rtol=0, atol=ATOL)


def test_stall_at_the_rounding_floor_is_accepted_within_the_floor():
    """Corrections and residuals of 3 tolerances that never shrink: the plain test never
    passes, the stall test accepts the iterate, which is within the error's size."""
    amplitude = 1.5 * ATOL
    solution = _solve(_floor_residual(amplitude), jnp.eye(3))
    assert solution.result == optx.RESULTS.successful
    assert int(solution.stats["num_steps"]) <= 4
    np.testing.assert_allclose(solution.value, ROOT, rtol=0, atol=amplitude * (1 + 1e-6))


def test_a_floor_far_above_the_tolerance_still_fails():
    solution = _solve(_floor_residual(STALL_FACTOR * ATOL), jnp.eye(3))
    assert solution.result != optx.RESULTS.successful


def test_slow_convergence_is_accepted_only_near_the_root():
    """A poor inverse (contraction c = 0.8) is accepted by the stall test once the
    correction is below STALL_FACTOR tolerances, and the iterate is then within
    STALL_FACTOR * c / (1 - c) tolerances of the root."""
    contraction = 0.8
    solution = _solve(lambda u, args: u - ROOT, (1 - contraction) * jnp.eye(3), max_steps=200)
    assert solution.result == optx.RESULTS.successful
    error = float(jnp.max(jnp.abs(solution.value - ROOT)))
    assert error <= STALL_FACTOR * contraction / (1 - contraction) * ATOL
    assert error > ATOL  # accepted by the stall test, not the plain one


@pytest.mark.parametrize("growth", [4.0, jnp.inf])
def test_growing_or_nonfinite_corrections_are_divergence(growth):
    solution = _solve(lambda u, args: growth * (u - ROOT) + 1.0, jnp.eye(3))
    assert solution.result == optx.RESULTS.nonlinear_divergence


def test_chord_inverse_pivots_only_where_needed_also_within_a_batch():
    """A dominant matrix and one whose first pivot is zero, alone and in one vmapped
    batch: each gets its exact inverse (the second only by pivoting)."""
    dominant = jnp.array([[1.0, 0.2, -0.1], [0.3, -1.0, 0.2], [0.0, 0.4, 1.0]])
    needs_pivoting = jnp.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    jitted = jax.jit(chord_inverse)
    for a in (dominant, needs_pivoting):
        np.testing.assert_allclose(jitted(a) @ a, jnp.eye(3), atol=1e-15)
    batch = jax.jit(jax.vmap(chord_inverse))(jnp.stack([dominant, needs_pivoting, dominant]))
    for a, inverse in zip((dominant, needs_pivoting, dominant), batch):
        np.testing.assert_allclose(inverse @ a, jnp.eye(3), atol=1e-15)
