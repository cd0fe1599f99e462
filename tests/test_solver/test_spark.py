"""SPARK (Lobatto IIIA-B-C-C*-D): order 2 against the index-1 reference, time symmetry,
the constraint at step ends to roundoff, an energy error that is neither roundoff nor
growing, per-trajectory failures, and the tableau-driven stepper with other tableaux."""

import functools
import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh
from nhjax._solver._spark_tableau import lobatto_coefficients, lobatto_constraint_weights

from ..helpers import fitted_order, reference_final_state, relative_energy_error, step_there_and_back


GEARBOX = nh.examples.gearbox()
QUARTIC = nh.examples.chaotic_quartic()
SLEIGH = nh.examples.chaplygin_sleigh()
DISK = nh.examples.rolling_disk()
METHOD = nh.SPARK()
RATTLE = nh.SPARK(nh.lobatto_spark_tableau(2, constraint_force="IIIB"))
LOBATTO_3 = nh.SPARK(nh.lobatto_spark_tableau(3))
STEP_SIZES = (0.2, 0.1, 0.05)
T1 = 5.0
# One compiled program per (system, method) instead of op-by-op dispatch.
there_and_back = eqx.filter_jit(step_there_and_back)


def _starts():
    return {
        "gearbox, k = 1": (GEARBOX, GEARBOX.random_initial_state(jax.random.key(0))),
        "quartic, k = 1, n = 7": (QUARTIC, QUARTIC.from_adapted(QUARTIC.initial_state(0.9))),
        "sleigh, q-dependent metric": (
            SLEIGH,
            SLEIGH.from_adapted(jnp.array([0.0, 0.0, 0.1, 0.3, -0.6]), SLEIGH.args),
        ),
        "disk, k = 2": (
            DISK,
            DISK.from_adapted(DISK.initial_state(theta=0.2, rho1=1.0, rho2=0.5), DISK.args),
        ),
    }


@functools.cache
def _reference(name):
    example, y0 = _starts()[name]
    return reference_final_state(example.canonical, y0, T1, example.args)


def _end_state_errors(name, method):
    """max |y(T1) - reference| for each step size, from one compiled program: every run
    has the same n_steps and save_every (dt is traced), and the save at step T1/h is
    read off."""
    example, y0 = _starts()[name]
    steps = [round(T1 / h) for h in STEP_SIZES]
    every = math.gcd(*steps)
    reference = _reference(name)
    errors = []
    for h, m in zip(STEP_SIZES, steps):
        solution = nh.integrate(
            example.canonical, method, y0, h, max(steps), args=example.args, save_every=every
        )
        assert solution.result == nh.RESULTS.successful
        final = jax.tree.map(lambda y: y[m // every], solution.ys)
        errors.append(max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(final, reference)))
    return errors


@pytest.mark.parametrize("name", ["gearbox, k = 1", "quartic, k = 1, n = 7"])
def test_second_order_against_the_index1_reference(name):
    errors = _end_state_errors(name, METHOD)
    assert METHOD.order(None) == 2
    assert 1.8 <= fitted_order(STEP_SIZES, errors) <= 2.2, errors


def test_other_tableaux_run_through_the_same_stepper_at_their_orders():
    """The nonholonomic RATTLE (constraint force on IIIB) is a different second-order
    method; the 3-stage Lobatto IIIA-B-C-C*-D tableau gives order 4 = 2s - 2."""
    name = "gearbox, k = 1"
    default = _end_state_errors(name, METHOD)
    rattle = _end_state_errors(name, RATTLE)
    three_stage = _end_state_errors(name, LOBATTO_3)
    assert 1.8 <= fitted_order(STEP_SIZES, rattle) <= 2.2, rattle
    assert abs(rattle[-1] - default[-1]) > 0.05 * default[-1], (rattle, default)
    assert LOBATTO_3.order(None) == 4
    assert 3.7 <= fitted_order(STEP_SIZES, three_stage) <= 4.3, three_stage
    assert three_stage[-1] < 1e-2 * default[-1]


@pytest.mark.parametrize("name", list(_starts()))
def test_time_symmetric(name):
    """A step with h, then one with -h, returns to the start."""
    example, y0 = _starts()[name]
    back, results = there_and_back(example.canonical, METHOD, y0, 0.2, example.args)
    assert all(result == diffrax.RESULTS.successful for result in results)
    np.testing.assert_allclose(back[0], y0[0], atol=1e-14)
    np.testing.assert_allclose(back[1], y0[1], atol=1e-14)


def test_a_constraint_force_tableau_that_is_not_self_adjoint_breaks_the_symmetry():
    """The same check fails by many orders of magnitude when the constraint force uses
    IIIC alone (IIIC is the adjoint of IIIC*, not of itself)."""
    coefficients = lobatto_coefficients(2)
    tableau = nh.SPARKTableau(
        c=coefficients["c"],
        b=coefficients["b"],
        velocity=coefficients["IIIA"],
        force=coefficients["IIIB"],
        constraint_force=coefficients["IIIC"],
        constraint_weights=lobatto_constraint_weights(coefficients["b"], coefficients["c"]),
        order=1,
    )
    example, y0 = _starts()["quartic, k = 1, n = 7"]
    back, results = there_and_back(example.canonical, nh.SPARK(tableau), y0, 0.2)
    assert all(result == diffrax.RESULTS.successful for result in results)
    assert float(jnp.max(jnp.abs(back[1] - y0[1]))) > 1e-6


def test_constraint_to_roundoff_and_energy_error_bounded_over_ten_thousand_steps():
    """g(q1, p1) = 0 is one of the step's equations: it holds at every step's end. The
    energy is not conserved: its error is far above roundoff but stays small (the
    method is symmetric, not energy-preserving)."""
    _, y0 = _starts()["quartic, k = 1, n = 7"]
    solution = nh.integrate(QUARTIC.canonical, METHOD, y0, 0.05, 10_000, save_every=10)
    assert solution.result == nh.RESULTS.successful
    assert float(jnp.max(jnp.abs(solution.constraint))) <= 1e-14
    energy_error = relative_energy_error(solution)
    assert 1e-5 <= energy_error <= 1e-2, energy_error


@pytest.mark.parametrize("name", ["sleigh, q-dependent metric", "disk, k = 2"])
def test_constraint_to_roundoff_with_a_q_dependent_metric_and_two_constraints(name):
    example, y0 = _starts()[name]
    solution = nh.integrate(example.canonical, METHOD, y0, 0.1, 2_000, args=example.args, save_every=10)
    assert solution.result == nh.RESULTS.successful
    assert float(jnp.max(jnp.abs(solution.constraint))) <= 1e-14


def test_result_codes_per_trajectory_under_vmap():
    """A batch of three: a good start; a start with NaN momenta; and one whose
    Hamiltonian turns NaN at q3 > 1. q3 is a free rotation (A has no q3 column), so
    q3 = 0.55 + t from p3 = 1, and the fifth step, to q3 = 1.05, fails, as a non-finite step. Each has its
    own code; the good one is the same as in a batch of good starts only."""

    def hamiltonian(q, p, args):
        return 0.5 * (p @ p + q[0] ** 2 + q[1] ** 2) + 0.0 * jnp.sqrt(1.0 - q[2])

    def constraints(q, args):
        return jnp.array([[1.0, 0.5, 0.0]], dtype=q.dtype)

    system = nh.NonholonomicSystem(hamiltonian, constraints)

    def start(q3, broken):
        q = jnp.array([0.1, 0.2, q3])
        p = system.project_momentum(q, jnp.array([0.5, -0.5, 1.0]))
        return q, jnp.where(broken, jnp.nan, p)

    def run(y0):
        return nh.integrate(system, METHOD, y0, 0.1, 20, throw=False)

    starts = jax.vmap(start)(jnp.array([-3.0, -3.0, 0.55]), jnp.array([False, True, False]))
    batch = jax.vmap(run)(starts)
    assert bool((batch.result == nh.RESULTS.successful)[0])
    assert bool((batch.result == nh.RESULTS.nonfinite_initial_state)[1])
    assert bool((batch.result == nh.RESULTS.nonfinite_step)[2])
    assert bool(jnp.all(jnp.isfinite(batch.ys[0][0])))
    assert not bool(jnp.any(jnp.isfinite(batch.ys[0][1])))
    assert bool(jnp.all(jnp.isfinite(batch.ys[0][2, :5])))
    assert not bool(jnp.any(jnp.isfinite(batch.ys[0][2, 5:])))
    good = jax.vmap(run)(jax.tree.map(lambda y: jnp.broadcast_to(y[0], y.shape), starts))
    assert bool(jnp.all(good.result == nh.RESULTS.successful))
    np.testing.assert_allclose(batch.ys[0][0], good.ys[0][1], atol=1e-14)
    np.testing.assert_allclose(batch.ys[1][0], good.ys[1][1], atol=1e-14)


def test_under_jit_with_a_traced_step_size():
    example, y0 = _starts()["gearbox, k = 1"]

    @jax.jit
    def final_state(y0, dt):
        solution = nh.integrate(example.canonical, METHOD, y0, dt, 100, save_every=25)
        return jax.tree.map(lambda y: y[-1], solution.ys), solution.result

    (q, p), result = final_state(y0, 0.05)
    assert result == nh.RESULTS.successful
    direct = nh.integrate(example.canonical, METHOD, y0, 0.05, 100, save_every=25)
    np.testing.assert_allclose(q, direct.ys[0][-1], atol=1e-14)
    np.testing.assert_allclose(p, direct.ys[1][-1], atol=1e-14)
    (q_large, _), _ = final_state(y0, 0.1)
    assert float(jnp.max(jnp.abs(q_large - q))) > 1e-3  # dt is traced, not baked in


def test_float32():
    """The float64 trajectory to tens of float32 ulps over 10 time units (roundoff
    then accumulates as a phase error), the same energy error as in float64 (it is the
    method's), and the constraint to a few float32 ulps over 100 time units."""
    example, y0 = _starts()["gearbox, k = 1"]
    y0_32 = jax.tree.map(lambda y: y.astype(jnp.float32), y0)
    single = nh.integrate(example.canonical, METHOD, y0_32, 0.1, 1000, save_every=10)
    double = nh.integrate(example.canonical, METHOD, y0, 0.1, 1000, save_every=10)
    assert single.ys[0].dtype == jnp.float32
    assert single.result == nh.RESULTS.successful
    eps = float(jnp.finfo(jnp.float32).eps)
    assert float(jnp.max(jnp.abs(single.constraint))) <= 16 * eps
    difference = max(float(jnp.max(jnp.abs(a[:11] - b[:11]))) for a, b in zip(single.ys, double.ys))
    assert difference <= 200 * eps, difference
    assert abs(relative_energy_error(single) - relative_energy_error(double)) <= 100 * eps


def test_lobatto_tableaux():
    """The s-stage construction reproduces the named 2-stage tableau exactly and the
    known 3-stage rational coefficients; IIIA, IIIB, IIID are self-adjoint."""
    assert nh.lobatto_spark_tableau(2) == nh.LOBATTO_IIIA_B_C_CSTAR_D_2
    assert nh.SPARK().tableau == nh.LOBATTO_IIIA_B_C_CSTAR_D_2
    three = lobatto_coefficients(3)
    np.testing.assert_allclose(three["b"], [1 / 6, 2 / 3, 1 / 6], atol=1e-15)
    known = {
        "IIIA": [[0, 0, 0], [5 / 24, 1 / 3, -1 / 24], [1 / 6, 2 / 3, 1 / 6]],
        "IIIB": [[1 / 6, -1 / 6, 0], [1 / 6, 1 / 3, 0], [1 / 6, 5 / 6, 0]],
        "IIIC": [[1 / 6, -1 / 3, 1 / 6], [1 / 6, 5 / 12, -1 / 12], [1 / 6, 2 / 3, 1 / 6]],
        "IIIC*": [[0, 0, 0], [1 / 4, 1 / 4, 0], [0, 1, 0]],
    }
    for name, matrix in known.items():
        np.testing.assert_allclose(three[name], matrix, atol=1e-15)
    for s in (2, 3, 4, 5):
        coefficients = lobatto_coefficients(s)
        b = coefficients["b"]
        for name in ("IIIA", "IIIB", "IIID"):
            matrix = coefficients[name]
            np.testing.assert_allclose(matrix + matrix[::-1, ::-1], np.broadcast_to(b, (s, s)), atol=1e-14)


def test_invalid_tableaux_are_rejected():
    two = lobatto_coefficients(2)
    valid = dict(
        c=two["c"],
        b=two["b"],
        velocity=two["IIIA"],
        force=two["IIIB"],
        constraint_force=two["IIID"],
        constraint_weights=[[0.5, 0.5]],
        order=2,
    )
    nh.SPARKTableau(**valid)
    for change, message in (
        (dict(constraint_weights=[[0.5, 0.5], [0.0, 1.0]]), "stage constraint"),
        (dict(force=np.eye(3)), "shape"),
        (dict(b=[0.5, 0.6]), "sum to 1"),
        (dict(velocity=[[0.0, np.nan], [0.5, 0.5]]), "finite"),
    ):
        with pytest.raises(ValueError, match=message):
            nh.SPARKTableau(**{**valid, **change})
    with pytest.raises(ValueError, match="constraint_force"):
        nh.lobatto_spark_tableau(2, constraint_force="IIIC")
    with pytest.raises(TypeError, match="SPARKTableau"):
        nh.SPARK(tableau=two)
