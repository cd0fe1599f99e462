"""SPARK (Jay's Lobatto SPARK methods): the tableau-driven stepper with other tableaux, what
a tableau that is not self-adjoint does, a traced step size, float32, and the Lobatto
tableaux. (Order, the constraint to roundoff, the energy error and symmetry:
test_methods.py; per-trajectory failures: test_faults.py.)"""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh
from nhjax._solver._spark_tableau import lobatto_coefficients, lobatto_constraint_weights

from ..helpers import canonical_starts, final_state_errors, fitted_order, reference_final_state, relative_energy_error, step_there_and_back


METHOD = nh.SPARK()
IIID = nh.SPARK(nh.LOBATTO_IIIA_B_C_CSTAR_D_2)
LOBATTO_3 = nh.SPARK(nh.lobatto_spark_tableau(3))
STEP_SIZES = (0.2, 0.1, 0.05)
T1 = 5.0
# One compiled program per (system, method) instead of op-by-op dispatch.
there_and_back = eqx.filter_jit(step_there_and_back)


STARTS = canonical_starts()


@functools.cache
def _reference(name):
    example, y0 = STARTS[name]
    return reference_final_state(example.canonical, y0, T1, example.args)


def _end_state_errors(name, method):
    """max |y(T1) - reference| for each step size, from one compiled program."""
    example, y0 = STARTS[name]
    return final_state_errors(example.canonical, method, y0, T1, STEP_SIZES, _reference(name), example.args)


def test_other_tableaux_run_through_the_same_stepper_at_their_orders():
    """The constraint force on IIID instead of IIIB is a different second-order method,
    time-symmetric too; the 3-stage Lobatto IIIA-B-C-C*-D tableau gives order 4 = 2s - 2."""
    name = "gearbox, M = I"
    default = _end_state_errors(name, METHOD)
    iiid = _end_state_errors(name, IIID)
    three_stage = _end_state_errors(name, LOBATTO_3)
    assert 1.8 <= fitted_order(STEP_SIZES, iiid) <= 2.2, iiid
    assert abs(iiid[-1] - default[-1]) > 0.05 * default[-1], (iiid, default)
    example, y0 = STARTS[name]
    back, results = there_and_back(example.canonical, IIID, y0, 0.2)
    assert all(result == diffrax.RESULTS.successful for result in results)
    for a, b in zip(back, y0):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-14)
    assert LOBATTO_3.order(None) == 4
    assert 3.7 <= fitted_order(STEP_SIZES, three_stage) <= 4.3, three_stage
    assert three_stage[-1] < 1e-2 * default[-1]


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
    example, y0 = STARTS["quartic, n = 7"]
    back, results = there_and_back(example.canonical, nh.SPARK(tableau), y0, 0.2)
    assert all(result == diffrax.RESULTS.successful for result in results)
    assert float(jnp.max(jnp.abs(back[1] - y0[1]))) > 1e-6


def test_under_jit_with_a_traced_step_size():
    example, y0 = STARTS["gearbox, M = I"]

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
    example, y0 = STARTS["gearbox, M = I"]
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
    assert nh.lobatto_spark_tableau(2, constraint_force="IIIB") == nh.LOBATTO_IIIA_B_2
    assert nh.SPARK().tableau == nh.LOBATTO_IIIA_B_2
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


class _EveryStageUnknown(nh.SPARK):
    """SPARK with every stage an unknown of the step, the general count 2ns + ks."""

    def _q_stages(self):
        every = tuple(range(self.tableau.stages))
        return every, every

    _p_stages = _q_stages


def test_stages_that_the_tableau_fixes_are_not_unknowns():
    """Lobatto IIIA's zero first row gives Q_1 = q_0; IIIB's equal rows at s = 2 give
    P_1 = P_2. Left out of the unknowns, they leave the step the same as with every stage
    an unknown (to the root finder's tolerance), from a system of 2n + 2k unknowns for
    the default tableau instead of 4n + 2k."""
    assert nh.LOBATTO_IIIA_B_2.stage_unknowns("velocity") == ((1,), (-1, 0))
    assert nh.LOBATTO_IIIA_B_2.stage_unknowns("force", "constraint_force") == ((0,), (0, 0))
    assert nh.LOBATTO_IIIA_B_C_CSTAR_D_2.stage_unknowns("force", "constraint_force") == ((0, 1), (0, 1))
    assert LOBATTO_3.tableau.stage_unknowns("velocity") == ((1, 2), (-1, 0, 1))
    assert LOBATTO_3.tableau.stage_unknowns("force", "constraint_force") == ((0, 1, 2), (0, 1, 2))
    example, y0 = STARTS["disk, k = 2"]
    n, k = y0[0].shape[0], example.canonical.constraints(y0[0], example.args).shape[0]
    for method, count in ((METHOD, 2 * n + 2 * k), (IIID, 3 * n + 2 * k), (LOBATTO_3, 5 * n + 3 * k)):
        every = _EveryStageUnknown(method.tableau)
        unknowns = [m.setup(example.canonical, 0.0, 0.05, y0, example.args, None)[0].shape[0] for m in (method, every)]
        assert unknowns == [count, 2 * n * method.tableau.stages + k * method.tableau.stages], unknowns
        ends = [
            nh.integrate(example.canonical, m, y0, 0.05, 20, args=example.args, save_every=20).ys for m in (method, every)
        ]
        for a, b in zip(*ends):
            np.testing.assert_allclose(a[-1], b[-1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("s", [2, 3, 4, 5])
def test_the_stage_constraints_are_those_of_the_lobatto_iiia_form(s):
    """The weights b_j c_j^(i-1) and the rows 2..s of Lobatto IIIA (the form in which
    Jay's stage constraints are also written) span the same s - 1 equations; the rows of
    IIIC*, other equations, do not."""
    coefficients = lobatto_coefficients(s)
    weights = lobatto_constraint_weights(coefficients["b"], coefficients["c"])
    rank = lambda matrix: np.linalg.matrix_rank(matrix, tol=1e-10)  # noqa: E731
    assert rank(weights) == rank(coefficients["IIIA"][1:]) == s - 1
    assert rank(np.concatenate([weights, coefficients["IIIA"][1:]])) == s - 1
    assert rank(np.concatenate([weights, coefficients["IIIC*"][1:]])) > s - 1


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
