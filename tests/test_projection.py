"""nhjax.Projection: diffrax's solvers with every step's end projected onto the energy
level and the constraint."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh

from .helpers import (
    canonical_starts,
    check_float32,
    check_per_trajectory_result_codes,
    final_state_errors,
    fitted_order,
    reference_final_state,
    relative_energy_error,
)


EPS = float(jnp.finfo(jnp.float64).eps)
PROJECTED_TSIT5 = nh.Projection(diffrax.Tsit5())


def _gearbox():
    gearbox = nh.examples.gearbox()
    return gearbox, gearbox.random_initial_state(jax.random.key(0))


def test_energy_and_constraint_to_roundoff_over_ten_thousand_steps_where_the_solver_drifts():
    gearbox, y0 = _gearbox()
    projected = nh.integrate(gearbox.canonical, PROJECTED_TSIT5, y0, 0.1, 10_000, save_every=10)
    plain = nh.integrate(gearbox.canonical, diffrax.Tsit5(), y0, 0.1, 10_000, save_every=10)
    # Without the projection both invariants drift far above roundoff.
    assert relative_energy_error(plain) > 1e-9
    assert float(jnp.max(jnp.abs(plain.constraint))) > 1e-9
    assert relative_energy_error(projected) < 20 * EPS
    assert float(jnp.max(jnp.abs(projected.constraint))) < 10 * EPS
    # A simplified Newton correction and the check that confirms it.
    assert int(projected.stats["max_root_find_steps"]) <= 3


def test_energy_only_on_a_skew_gradient_system():
    quartic = nh.examples.chaotic_quartic(3)
    x0 = quartic.initial_state(0.7)
    projected = nh.integrate(quartic.adapted, PROJECTED_TSIT5, x0, 0.1, 2000, save_every=10)
    plain = nh.integrate(quartic.adapted, diffrax.Tsit5(), x0, 0.1, 2000, save_every=10)
    assert relative_energy_error(plain) > 1e-8
    assert relative_energy_error(projected) < 20 * EPS


@pytest.mark.parametrize(
    "solver, order, start, step_sizes",
    [
        (diffrax.Tsit5(), 5, "disk, k = 2", (0.1, 0.05, 0.025)),
        (diffrax.Dopri8(), 8, "quartic, n = 7", (0.4, 0.25, 0.2)),
    ],
    ids=["tsit5", "dopri8"],
)
def test_keeps_the_solvers_order(solver, order, start, step_sizes):
    example, y0 = canonical_starts()[start]
    reference = reference_final_state(example.canonical, y0, 10.0, example.args)
    errors = final_state_errors(
        example.canonical, nh.Projection(solver), y0, 10.0, step_sizes, reference, example.args
    )
    assert min(errors) > 1e-11  # above the reference's error
    assert order - 0.3 <= fitted_order(step_sizes, errors) <= order + 0.6, errors


def test_adaptive_saves_lie_on_the_invariant_set():
    """Every saved time is a step end: the saves keep the invariants to roundoff, which
    the linear interpolation between step ends would not."""
    gearbox, y0 = _gearbox()
    save_at = jnp.linspace(0.0, 10.0, 23)
    solution = nh.integrate_adaptive(
        gearbox.canonical, y0, 10.0, save_at=save_at, method=nh.Projection(diffrax.Dopri8()), rtol=1e-8, atol=1e-8
    )
    plain = nh.integrate_adaptive(gearbox.canonical, y0, 10.0, save_at=save_at, rtol=1e-8, atol=1e-8)
    assert relative_energy_error(plain) > 1e-10
    assert relative_energy_error(solution) < 10 * EPS
    assert float(jnp.max(jnp.abs(solution.constraint))) < 10 * EPS
    np.testing.assert_array_equal(solution.ts, save_at)
    reference = reference_final_state(gearbox.canonical, y0, 10.0)
    for leaf, exact in zip(solution.ys, reference):
        np.testing.assert_allclose(leaf[-1], exact, rtol=0, atol=1e-7)
    # Steps cut short to land on a save end nearly on the set: at most a correction and
    # its check anywhere.
    assert 0 < int(solution.stats["max_root_find_steps"]) <= 3


def test_derivatives_agree_with_finite_differences():
    gearbox, (q0, p0) = _gearbox()
    system = gearbox.canonical

    def loss(theta, adjoint=None):
        q = q0.at[2].add(theta)
        p = system.project_momentum(q, p0 * (1 + theta))
        # Large steps: the projection's share in the derivative is of the size of
        # the solver's local error, which must stand out from the differences' error.
        solution = nh.integrate(system, PROJECTED_TSIT5, (q, p), 0.5, 10, save_every=10, adjoint=adjoint)
        return jnp.sum(jnp.cos(jnp.arange(3.0)) * solution.ys[0][-1]) + jnp.sum(solution.ys[1][-1] ** 2)

    theta = 0.1
    reverse = float(jax.grad(loss)(theta))
    forward = float(jax.jacfwd(lambda theta: loss(theta, diffrax.ForwardMode()))(theta))
    step = 1e-5
    difference = (float(loss(theta + step)) - float(loss(theta - step))) / (2 * step)
    assert reverse == pytest.approx(difference, rel=1e-8)
    assert forward == pytest.approx(reverse, rel=1e-10, abs=1e-12)


def test_a_state_at_rest_at_an_equilibrium_stays_there():
    """grad H = 0 makes the projection's matrix singular: a step that already ends on
    the set is kept, not failed."""
    angle = 0.0
    for _ in range(50):  # Newton on dV/dq3 = -sin q3 - 0.4 cos 2q3 = 0
        angle -= (-np.sin(angle) - 0.4 * np.cos(2 * angle)) / (-np.cos(angle) + 0.8 * np.sin(2 * angle))
    gearbox = nh.examples.gearbox()
    y0 = (jnp.array([0.0, 0.0, angle]), jnp.zeros(3))
    solution = nh.integrate(gearbox.canonical, PROJECTED_TSIT5, y0, 0.1, 10)
    assert solution.result == nh.RESULTS.successful
    np.testing.assert_allclose(solution.ys[0][-1], y0[0], rtol=0, atol=1e-14)
    np.testing.assert_allclose(solution.ys[1][-1], y0[1], rtol=0, atol=1e-14)


def test_a_projection_that_cannot_converge_fails_with_its_own_code():
    gearbox, y0 = _gearbox()
    hurried = nh.Projection(diffrax.Tsit5(), root_find_max_steps=1)
    solution = nh.integrate(gearbox.canonical, hurried, y0, 0.1, 5, throw=False)
    assert solution.result == nh.RESULTS.projection_failed
    assert not bool(jnp.any(jnp.isfinite(solution.ys[0][1:])))
    with pytest.raises(RuntimeError, match="projection of a step's end"):
        nh.integrate(gearbox.canonical, hurried, y0, 0.1, 5)


def test_per_trajectory_result_codes():
    check_per_trajectory_result_codes(PROJECTED_TSIT5)


def test_float32():
    gearbox, y0 = _gearbox()
    check_float32(PROJECTED_TSIT5, gearbox, y0)


@pytest.mark.parametrize(
    "solver, message",
    [
        (nh.GonzalezR(), "nhjax method"),
        (nh.Projection(diffrax.Tsit5()), "nhjax method"),
        (nh.Composition(nh.GonzalezR()), "Composition is an nhjax method"),
        ("Tsit5", "wraps a diffrax solver"),
    ],
    ids=["nhjax method", "nested", "composition", "not a solver"],
)
def test_refuses_what_it_cannot_project(solver, message):
    with pytest.raises(ValueError, match=message):
        nh.Projection(solver)


def test_refuses_a_bad_iteration_limit():
    with pytest.raises(ValueError, match="root_find_max_steps"):
        nh.Projection(diffrax.Tsit5(), root_find_max_steps=0)
