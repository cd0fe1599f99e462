"""EnergyPreservingCollocation beyond the shared properties (tests/test_solver/
test_methods.py runs its invariants and symmetry on the canonical examples): its fitted
orders 4 and 6 against independent references on five systems, in both forms it takes,
and orders 8 to 12 on two;
its energy to roundoff on a skew-gradient system at large steps; its tableau against
the Gauss method's published coefficients; and its refusals."""

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh
from nhjax._linalg import SEQUENTIAL_BYTES
from nhjax._solver._collocation_tableau import collocation_tableau
from nhjax._solver.base import HISTORY, rounding_floor

from ..helpers import check_float32, check_per_trajectory_result_codes, fitted_order


T1 = 4.0
# Step sizes per order in the asymptotic regime, with errors above the references'
# (the gearbox's order-6 error constant is large: smaller steps).
STEP_SIZES = {4: (0.4, 0.2, 0.1), 6: (0.5, 0.25, 0.125)}
CASES = {
    "rolling disk": ("disk", "canonical", dict(theta=0.2), STEP_SIZES),
    "Suslov (skew-gradient)": ("suslov", "adapted", {}, STEP_SIZES),
    "gearbox": ("gearbox", "canonical", {}, {4: STEP_SIZES[4], 6: (0.25, 0.125, 0.0625)}),
    "quartic": ("quartic", "canonical", dict(angle=0.9), STEP_SIZES),
    "sleigh": ("sleigh", "canonical", dict(x1=0.0, rho1=2.0), STEP_SIZES),
}


def _distance(y, reference) -> float:
    return max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(y), jax.tree.leaves(reference)))


def _check_fitted_orders(case, step_sizes, tolerance):
    """The fitted order over three step sizes within [p - 0.3, p + 0.6] against Dopri8
    at rtol = atol = `tolerance` (the index-1 ODE for canonical systems, the
    skew-gradient field itself for Suslov), with the energy and, on canonical systems,
    the constraint to roundoff at every step."""
    name, form, choices, _ = CASES[case]
    example = nh.examples.EXAMPLES[name]()
    system, y0, args = example.system(form), example.start(form, **choices), example.args
    reference = nh.integrate_adaptive(system, y0, T1, args, rtol=tolerance, atol=tolerance, max_steps=1_000_000)
    final = jax.tree.map(lambda y: y[-1], reference.ys)
    for order, sizes in step_sizes.items():
        method = nh.EnergyPreservingCollocation(order)
        bound = round(T1 / min(sizes))  # one compiled program for the three sizes
        errors = []
        for h in sizes:
            solution = nh.integrate(system, method, y0, h, round(T1 / h), args, save_every=1, max_steps=bound)
            errors.append(_distance(jax.tree.map(lambda y: y[-1], solution.ys), final))
            energy = solution.energy
            assert float(jnp.max(jnp.abs(energy / energy[0] - 1))) <= 1e-13
            if solution.constraint is not None:
                assert float(jnp.max(jnp.abs(solution.constraint))) <= 1e-13
        assert min(errors) > 5e-13, errors  # above the reference's own error
        assert order - 0.3 <= fitted_order(sizes, errors) <= order + 0.6, (order, errors)


@pytest.mark.parametrize("case", list(CASES))
def test_orders_four_and_six_against_the_reference(case):
    _check_fitted_orders(case, CASES[case][3], 1e-13)


# Orders 8 to 12 at steps where the errors are above those of references at 1e-15 and
# in the asymptotic regime (longer on the smooth disk).
HIGH_ORDER_STEP_SIZES = {
    "quartic": {8: (0.25, 0.2, 0.125), 10: (0.5, 0.4, 0.25), 12: (0.8, 0.5, 0.4)},
    "rolling disk": {10: (4 / 3, 1.0, 0.8)},
}


@pytest.mark.parametrize("case", list(HIGH_ORDER_STEP_SIZES))
def test_orders_eight_to_twelve_against_the_reference(case):
    _check_fitted_orders(case, HIGH_ORDER_STEP_SIZES[case], 1e-15)


def test_energy_and_symmetry_on_a_skew_gradient_system_at_large_steps():
    """The chaotic quartic's reduced equations (a skew-gradient system whose H is quartic,
    so that grad H . du/dt along the step is a polynomial of degree 7 in time, beyond
    the two-point Gauss rule of order 4): at h = 0.5 the quadrature's own energy defect,
    H(x1) - H(x0) - sum_i b_i G_i . Z_i with the uncorrected G_i, is far above roundoff,
    and the corrected method keeps the energy to roundoff over 200 steps; a step with h
    then -h returns to the start."""
    example = nh.examples.EXAMPLES["quartic"]()
    system, x0 = example.adapted, example.start("adapted", angle=0.9)
    for order in (4, 6, 12):
        method = nh.EnergyPreservingCollocation(order)
        solution = nh.integrate(system, method, x0, 0.5, 200)
        assert float(jnp.max(jnp.abs(solution.energy / solution.energy[0] - 1))) <= 1e-13
        state = method.init(system, 0.0, 0.5, x0, None)
        *_, root = method.solve_step(system, 0.0, 0.5, x0, None, state)
        x1, _, _, state, _ = method.step(system, 0.0, 0.5, x0, None, state, False)
        back, *_ = method.step(system, 0.5, 0.0, x1, None, state, False)
        # Returned to roundoff, amplified by the stages: at h = 0.5, orders 4 to 12 came
        # back to 1, 1.5, 3.5, 11.5 and 47.5 eps on an AMD EPYC (no AVX-512), the high
        # orders' large tableau coefficients cancelling in the stages' sums.
        np.testing.assert_allclose(back, x0, rtol=0, atol=100 * np.finfo(back.dtype).eps)
        if order == 4:
            tableau = method.tableau()
            increments = root.reshape(method.stages, -1) * (1 + jnp.abs(x0))
            stages = x0 + jnp.asarray(tableau.a) @ increments
            gradients = jax.vmap(lambda x: jax.grad(system.hamiltonian)(x, None))(stages)
            quadrature = jnp.asarray(tableau.b) @ jnp.sum(gradients * increments, axis=1)
            defect = float(system.hamiltonian(x1, None) - system.hamiltonian(x0, None) - quadrature)
            assert abs(defect) > 1e-8 * abs(float(system.hamiltonian(x0, None))), defect


def test_the_tableau_is_the_gauss_method():
    """Two stages: the Gauss method's nodes 1/2 -+ sqrt(3)/6 and Butcher matrix
    (Hairer, Nørsett & Wanner, Table II.7.3); three stages: the nodes
    1/2 -+ sqrt(15)/10 and 1/2 with weights 5/18, 4/9, 5/18. With the quadrature at the
    collocation nodes its weights select each node's own gradient."""
    two = collocation_tableau(2, 2)
    root3 = math.sqrt(3.0)
    np.testing.assert_allclose(two.c, [0.5 - root3 / 6, 0.5 + root3 / 6], atol=1e-15)
    np.testing.assert_allclose(two.a, [[0.25, 0.25 - root3 / 6], [0.25 + root3 / 6, 0.25]], atol=1e-15)
    np.testing.assert_allclose(two.b, [0.5, 0.5], atol=1e-15)
    np.testing.assert_allclose(two.quadrature_weights, np.eye(2), atol=1e-15)
    three = collocation_tableau(3, 5)
    np.testing.assert_allclose(three.c, [0.5 - math.sqrt(15) / 10, 0.5, 0.5 + math.sqrt(15) / 10], atol=1e-15)
    np.testing.assert_allclose(three.b, [5 / 18, 4 / 9, 5 / 18], atol=1e-15)
    # The quadrature reproduces the projection of a polynomial of degree 3 on l_i/b_i.
    g = np.polynomial.Polynomial([0.3, -1.0, 2.0, 0.7])
    sigma = (np.polynomial.legendre.leggauss(5)[0] + 1) / 2
    exact = []
    for i in range(3):
        others = np.delete(three.c, i)
        lagrange = np.polynomial.Polynomial.fromroots(others) / np.prod(three.c[i] - others)
        integral = (lagrange * g).integ()
        exact.append((integral(1.0) - integral(0.0)) / three.b[i])
    np.testing.assert_allclose(three.quadrature_weights @ g(sigma), exact, atol=1e-14)


@pytest.mark.parametrize("order", [4, 6, 8, 10, 12])
def test_the_chord_matrix_comes_with_its_inverse_and_its_rounding_floor(order):
    """`chord_matrix` returns the field's derivative F, from which `chord_jacobian`
    assembles I - h (a x F), and that matrix's inverse, formed by the Gauss matrix's
    eigenvalues (complex pairs, and the real eigenvalue of orders 6 and 10) in real
    arithmetic; `chord_floor` reads from F what `rounding_floor` reads from the
    assembled matrix. On the quartic's reduced form (13 unknowns per stage: matrix
    products by dots) and the gearbox's (5: by broadcasts), at a step of 0.7, where the
    matrix is far from I."""
    quartic, gearbox = nh.examples.chaotic_quartic(3), nh.examples.gearbox()
    method = nh.EnergyPreservingCollocation(order)
    for system, y0, blocked in (
        (quartic.canonical, quartic.from_adapted(quartic.initial_state(0.7)), False),
        # Its inverted blocks small together up to order 8 (5 unknowns a stage).
        (gearbox.canonical, gearbox.random_initial_state(jax.random.key(0)), order <= 8),
    ):
        h = jnp.asarray(0.7)
        guess, derivative, inverse, jacobian, floors = _chord_matrices(method, system, h, y0)
        size = guess.shape[0] // method.stages
        np.testing.assert_array_equal(
            jacobian[:size, :size], jnp.eye(size) - h * method.tableau().a[0, 0] * derivative
        )
        assert float(jnp.max(jnp.abs(jacobian - jnp.eye(guess.shape[0])))) > 0.05
        np.testing.assert_allclose(jnp.vstack(inverse) @ jacobian, jnp.eye(guess.shape[0]), rtol=0, atol=1e-13)
        if blocked:
            # In blocks of rows small enough for XLA:CPU to run a step in sequence.
            assert isinstance(inverse, tuple) and len(inverse) >= method.stages
            assert max(block.nbytes for block in inverse) <= SEQUENTIAL_BYTES
        else:
            assert not isinstance(inverse, tuple)
        np.testing.assert_allclose(*floors, rtol=1e-14)


@eqx.filter_jit
def _chord_matrices(method, system, h, y0):
    """At a step's guess, moved away from the no-motion guess of a first step: the
    guess, `chord_matrix`'s F and inverse, `chord_jacobian`, and the rounding floor read
    both ways (`chord_floor` from F, `rounding_floor` from the assembled matrix). One
    program: evaluated eagerly, these compile their operations one by one."""
    guess, data = method.setup(system, 0.0, h, y0, None, method.initial_carry(system, y0, None))
    guess = guess + 0.01
    derivative, inverse = method.chord_matrix(guess, data)
    jacobian = method.chord_jacobian(guess, data)
    floors = method.chord_floor(derivative, data), rounding_floor(jacobian, *method.resolution(data))
    return guess, derivative, inverse, jacobian, floors


@eqx.filter_jit
def _guess_error_and_step(method, system, h, t0, y, state):
    """The error of a step's guess, relative to the increments it solves for, and the
    step."""
    guess, data = method.setup(system, t0, h, y, None, state.carry)
    y, _, _, state, result = method.step(system, t0, t0 + h, y, None, state, False)
    increments = state.carry.increments
    error = jnp.max(jnp.abs(data.scale * guess.reshape(increments.shape) - increments))
    return error / jnp.max(jnp.abs(increments)), y, state, result


def _guess_errors(method, system, y0, step_sizes):
    """The guesses' relative errors over consecutive steps of the given sizes."""
    state, y, t, errors = method.init(system, 0.0, step_sizes[0], y0, None), y0, 0.0, []
    for h in step_sizes:
        error, y, state, result = _guess_error_and_step(method, system, jnp.asarray(h), jnp.asarray(t), y, state)
        assert result == diffrax.RESULTS.successful
        errors.append(float(error))
        t += h
    return errors


def test_the_guess_is_of_order_history_once_that_many_steps_of_one_size_are_known():
    """On the gearbox at order 4 the guess is O(h^s) = O(h^2) from the root (the last
    polynomial extrapolated) until HISTORY steps of the step's size are known, then
    O(h^HISTORY) (the step ends' history); after a change of step size it is the
    extrapolation's again; and where the step is long against the motion (the quartic
    at order 12, h = 0.7) the extrapolation's (a history that extrapolates wildly
    would be several times the increments off)."""
    gearbox = nh.examples.gearbox()
    method = nh.EnergyPreservingCollocation(4)
    y0 = gearbox.random_initial_state(jax.random.key(0))
    sizes = (0.08, 0.04, 0.02)
    errors = np.array([_guess_errors(method, gearbox.canonical, y0, [h] * (HISTORY + 3)) for h in sizes])
    early, late = errors[:, HISTORY - 1], errors[:, HISTORY + 2]
    assert 1.7 <= fitted_order(sizes, early) <= 2.3, early
    assert fitted_order(sizes, late) >= HISTORY - 0.5, late
    assert late[-1] <= 1e-4 * early[-1], (early, late)
    # A change by 0.5%, which the two predictions would not tell apart.
    changed = _guess_errors(method, gearbox.canonical, y0, [0.02] * (HISTORY + 3) + [0.0199] * (HISTORY + 3))
    assert changed[HISTORY + 2] <= 1e-7 and 1e-5 <= changed[HISTORY + 3] <= 1e-3, changed
    assert changed[-1] <= 1e-7, changed
    quartic = nh.examples.chaotic_quartic(3)
    y0 = quartic.from_adapted(quartic.initial_state(0.7))
    long = _guess_errors(nh.EnergyPreservingCollocation(12), quartic.canonical, y0, [10 / 14] * (HISTORY + 4))
    assert max(long[HISTORY + 1:]) <= 1.5, long


def test_float32_and_per_trajectory_codes():
    gearbox = nh.examples.gearbox()
    check_float32(nh.EnergyPreservingCollocation(4), gearbox, gearbox.random_initial_state(jax.random.key(0)))
    check_per_trajectory_result_codes(nh.EnergyPreservingCollocation(4))


def test_ensembles_and_chunked_runs_are_the_single_run(tmp_path):
    """An ensemble of three sleigh states (a q-dependent metric) gives each state's
    single run to the root finder's tolerance, and a run in chunks of 20 steps the
    whole run."""
    sleigh = nh.examples.EXAMPLES["sleigh"]()
    method = nh.EnergyPreservingCollocation(6)
    starts = [sleigh.start("canonical", x1=0.0, rho1=rho) for rho in (0.3, 1.0, 2.0)]
    batch = jax.tree.map(lambda *y: jnp.stack(y), *starts)
    ensemble = nh.integrate_ensemble(sleigh.canonical, method, batch, 0.2, 40, args=sleigh.args)
    for i, start in enumerate(starts):
        single = nh.integrate(sleigh.canonical, method, start, 0.2, 40, args=sleigh.args)
        for leaf, single_leaf in zip(ensemble.ys, single.ys):
            np.testing.assert_allclose(leaf[i], single_leaf, rtol=0, atol=1e-12)
    chunked = nh.run_chunked(
        sleigh.canonical, method, starts[2], 0.2, 40, args=sleigh.args, directory=tmp_path, chunk_steps=20,
        progress=False,
    )
    whole = nh.integrate(sleigh.canonical, method, starts[2], 0.2, 40, args=sleigh.args)
    np.testing.assert_allclose(chunked.ys[1][-1], whole.ys[1][-1], rtol=0, atol=1e-12)
    assert int(chunked.stats["root_find_steps"]) > 0


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="order must be one of"):
        nh.EnergyPreservingCollocation(5)
    with pytest.raises(ValueError, match="order must be one of"):
        nh.EnergyPreservingCollocation(14)
    with pytest.raises(ValueError, match="order must be one of"):
        nh.EnergyPreservingCollocation(True)
    with pytest.raises(ValueError, match="quadrature_nodes must be an integer of at least 3"):
        nh.EnergyPreservingCollocation(6, quadrature_nodes=2)
    with pytest.raises(ValueError, match="NonholonomicSystem .* or a SkewGradientSystem, got ODETerm"):
        term = diffrax.ODETerm(lambda t, y, args: -y)
        nh.EnergyPreservingCollocation(4).initial_carry(term, jnp.ones(3), None)
