"""A method that keeps its chord matrix from step to step (`reuse_chord_matrix=True`,
`AbstractMethod.reuses_chord_matrix`): fewer matrices formed, the same run to the root
finder's tolerance, the same derivatives, and a fresh matrix wherever the kept one does
not serve (another step size, slow convergence, a failed root find)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.core import Var

import nhjax as nh
from nhjax._solver.base import ChordMemory, KEPT_STEPS, no_gradient

from ..helpers import canonical_starts, equations, relative_energy_error


STARTS = canonical_starts()
# (label, fresh, kept): a q-dependent metric for GONZALEZ-R and GONZALEZ-F, and the
# collocation.
CASES = {
    f"{name}, sleigh": (
        "sleigh, q-dependent M", method(reuse_chord_matrix=False), method(reuse_chord_matrix=True), 0.1, 200
    )
    for name, method in (("GONZALEZ-R", nh.GonzalezR), ("GONZALEZ-F", nh.GonzalezF))
}
CASES |= {
    "collocation 4, quartic": (
        "quartic, n = 7",
        nh.EnergyPreservingCollocation(4),
        nh.EnergyPreservingCollocation(4, reuse_chord_matrix=True),
        0.1,
        100,
    ),
}


def _distance(a, b) -> float:
    return max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


@pytest.mark.parametrize("case", list(CASES))
def test_a_kept_matrix_changes_the_iterations_not_the_run(case):
    label, fresh, kept, h, steps = CASES[case]
    example, y0 = STARTS[label]
    reference = nh.integrate(example.canonical, fresh, y0, h, steps, args=example.args, save_every=10)
    run = nh.integrate(example.canonical, kept, y0, h, steps, args=example.args, save_every=10)
    assert "chord_matrices" not in reference.stats
    formed = int(run.stats["chord_matrices"])
    # Formed at the first step and afresh at some others, kept at most (step sizes
    # t1 - t0 from accumulated times differ by rounding, and match).
    assert 1 <= formed <= steps // 2
    assert _distance(run.ys, reference.ys) <= 1e-12
    assert relative_energy_error(run) <= 1e-13
    if kept.keeps_constraint():
        assert float(jnp.max(jnp.abs(run.constraint))) <= 1e-14


@pytest.mark.parametrize("case", list(CASES))
def test_the_memory_of_an_unformed_matrix_has_the_form_of_a_formed_one(case):
    """The NaN a kept matrix's memory starts with, read off the unknowns where the
    method's matrix is a square one and its inverse, has the structure, shapes and
    dtypes of the matrix the method forms (traced for its shapes)."""
    label, _, kept, h, _ = CASES[case]
    example, y0 = STARTS[label]
    system = example.canonical
    carry = kept.initial_carry(system, y0, example.args)
    guess, data = kept.setup(system, jnp.asarray(0.0), jnp.asarray(h), y0, example.args, carry)
    unformed = kept.unformed_chord_matrix(guess, data)
    formed = jax.eval_shape(lambda: kept.chord_matrix(guess, data, kept=True))
    assert jax.tree.structure(unformed) == jax.tree.structure(formed)
    for nan, shape in zip(jax.tree.leaves(unformed), jax.tree.leaves(formed)):
        assert (nan.shape, nan.dtype) == (shape.shape, shape.dtype)
        assert bool(jnp.all(jnp.isnan(nan)))


def test_gonzalez_r_keeps_its_matrix_where_forming_it_is_dear():
    """By default GONZALEZ-R keeps its chord matrix where the metric depends on q or
    the reduced system has more than `KEPT_ABOVE_UNKNOWNS` unknowns, and not
    elsewhere; `True` and `False` choose."""
    sleigh, y0 = STARTS["sleigh, q-dependent M"]
    run = nh.integrate(sleigh.canonical, nh.GonzalezR(), y0, 0.1, 20, args=sleigh.args)
    assert 1 <= int(run.stats["chord_matrices"]) < 20
    gearbox, start = STARTS["gearbox, M = I"]
    assert not nh.GonzalezR().reuses_chord_matrix(gearbox.canonical, start, gearbox.args)
    assert nh.GonzalezR(reuse_chord_matrix=True).reuses_chord_matrix(gearbox.canonical, start, gearbox.args)
    assert not nh.GonzalezR(reuse_chord_matrix=False).reuses_chord_matrix(sleigh.canonical, y0, sleigh.args)

    for n, kept in ((36, False), (40, True)):  # 2n - n/4: 63 and 70 unknowns
        q = jnp.linspace(0.1, 0.5, n)
        assert nh.GonzalezR().reuses_chord_matrix(_unit_metric_system(n), (q, jnp.zeros(n)), None) == kept
    with pytest.raises(ValueError, match="reuse_chord_matrix"):
        nh.GonzalezR(reuse_chord_matrix="yes")


def _unit_metric_system(n):
    """M = I and n / 4 constraint rows."""

    def constraints(q, args):
        del args
        return jnp.eye(n, dtype=q.dtype)[: n // 4] * jnp.cos(q)

    return nh.NonholonomicSystem(lambda q, p, args: 0.5 * p @ p + jnp.sum(jnp.cos(q)), constraints)


def test_gonzalez_f_keeps_its_matrix_where_forming_it_is_dear():
    """By default GONZALEZ-F keeps its chord matrix where the metric depends on q or
    there are more than `KEPT_ABOVE_UNKNOWNS` unknowns (2n + k), as GONZALEZ-R does;
    `True` and `False` choose."""
    starts = {label: STARTS[label] for label in ("gearbox, M = I", "sleigh, q-dependent M", "disk, k = 2")}
    kept = {label: nh.GonzalezF().reuses_chord_matrix(ex.canonical, y0, ex.args) for label, (ex, y0) in starts.items()}
    # The disk's metric is a constant other than I.
    assert kept == {"gearbox, M = I": False, "sleigh, q-dependent M": True, "disk, k = 2": False}
    gearbox, start = starts["gearbox, M = I"]
    assert nh.GonzalezF(reuse_chord_matrix=True).reuses_chord_matrix(gearbox.canonical, start, gearbox.args)
    sleigh, y0 = starts["sleigh, q-dependent M"]
    assert not nh.GonzalezF(reuse_chord_matrix=False).reuses_chord_matrix(sleigh.canonical, y0, sleigh.args)
    run = nh.integrate(sleigh.canonical, nh.GonzalezF(), y0, 0.1, 20, args=sleigh.args)
    assert 1 <= int(run.stats["chord_matrices"]) < 20
    for n, expected in ((28, False), (32, True)):  # 63 and 72 unknowns
        q = jnp.linspace(0.1, 0.5, n)
        assert nh.GonzalezF().reuses_chord_matrix(_unit_metric_system(n), (q, jnp.zeros(n)), None) == expected
    with pytest.raises(ValueError, match="GonzalezF: reuse_chord_matrix"):
        nh.GonzalezF(reuse_chord_matrix=1)


def test_a_batch_keeps_each_trajectory_s_own_matrix():
    label, _, kept, h, steps = CASES["GONZALEZ-R, sleigh"]
    example, y0 = STARTS[label]
    states = jax.tree.map(lambda y: jnp.stack([y, 1.3 * y, 0.7 * y]), y0)
    states = (states[0], jax.vmap(lambda q, p: example.canonical.project_momentum(q, p, example.args))(*states))

    def run(y):
        return nh.integrate(example.canonical, kept, y, h, steps, args=example.args, save_every=steps)

    batch = jax.jit(jax.vmap(run))(states)
    for i in range(3):
        alone = run(jax.tree.map(lambda y: y[i], states))
        assert _distance(jax.tree.map(lambda y: y[i], batch.ys), alone.ys) <= 1e-12
        assert 1 <= int(batch.stats["chord_matrices"][i]) < steps


def test_derivatives_do_not_depend_on_the_kept_matrix():
    label, fresh, kept, h, steps = CASES["GONZALEZ-R, sleigh"]
    example, (q0, p0) = STARTS[label]

    def loss(method):
        def of(p):
            final = nh.integrate(example.canonical, method, (q0, p), h, 40, args=example.args, save_every=40).ys
            return jnp.sum(final[0][-1] ** 2) + jnp.sum(final[1][-1] ** 2)

        return of

    direction = jnp.ones_like(p0)
    kept_derivative = jax.jvp(loss(kept), (p0,), (direction,))[1]
    fresh_derivative = jax.jvp(loss(fresh), (p0,), (direction,))[1]
    assert abs(float(fresh_derivative)) > 0.1
    np.testing.assert_allclose(kept_derivative, fresh_derivative, rtol=1e-10)


def test_a_step_size_change_forms_a_fresh_matrix():
    """The triple jump's substeps take h1, h2, h1: the middle one, and the first after
    it, never find a matrix formed for their step size; only a step's first substep,
    after the last one of the step before, may keep one."""
    label, _, kept, h, steps = CASES["GONZALEZ-R, sleigh"]
    example, y0 = STARTS[label]
    run = nh.integrate(
        example.canonical, nh.Composition(kept, **nh.COMPOSITION_SCHEMES["triple-jump-4"]), y0, h, 20, args=example.args
    )
    formed = int(run.stats["chord_matrices"])
    assert 2 * 20 <= formed <= 3 * 20


def _step(label, method, h):
    """(method, residual data, guess) of the first step of `method` from the case's start."""
    example, y0 = STARTS[label]
    carry = method.initial_carry(example.canonical, y0, example.args)
    guess, data = method.setup(example.canonical, 0.0, h, y0, example.args, carry)
    return no_gradient(data), guess


# GONZALEZ-R's exact chord matrix, differenced, formed in two programs.
MATRIX_ROUNDING = 1e-8


def test_a_failing_kept_matrix_is_replaced_by_a_fresh_one():
    label, _, kept, h, _ = CASES["GONZALEZ-R, sleigh"]
    data, guess = _step(label, kept, h)
    root_finder = kept._root_finder(guess.dtype)
    fresh, jacobian, inverse, _ = kept._chord_solve(root_finder, guess, data, None)
    key = kept.chord_key(data)
    one = jnp.array(1, jnp.int32)
    # A matrix for this step size that cannot move the iterate: the root find fails
    # with it (too many iterations) and is done again with a fresh one.
    useless = ChordMemory(jacobian, jax.tree.map(jnp.zeros_like, inverse), key, fresh.steps, fresh.steps, one, one)
    solution, _, used, memory = kept._chord_solve(root_finder, guess, data, useless)
    assert solution.result == fresh.result
    # Formed in a branch of its own, so rounded apart from the fresh one above: the
    # root to rounding, the matrix (by forward differences, where a rounding apart
    # in the residual moves an entry by it over sqrt(eps)) to 1e-8.
    np.testing.assert_allclose(solution.value, fresh.value, rtol=0, atol=1e-15)
    np.testing.assert_allclose(jnp.vstack(used), jnp.vstack(inverse), rtol=0, atol=MATRIX_ROUNDING)
    assert int(solution.steps) == kept.root_find_max_steps + int(fresh.steps)
    assert int(memory.formed) == 2 and int(memory.fresh_iterations) == int(fresh.steps)
    # A matching key, but the last step needed more than one iteration more than
    # twice the matrix's first, or the matrix has served `KEPT_STEPS` steps: formed
    # afresh before the root find.
    slow = ChordMemory(jacobian, jax.tree.map(jnp.zeros_like, inverse), key, fresh.steps, 2 * fresh.steps + 2, one, one)
    old = ChordMemory(jacobian, jax.tree.map(jnp.zeros_like, inverse), key, fresh.steps, fresh.steps, one * KEPT_STEPS, one)
    for memory in (slow, old):
        solution, _, used, memory = kept._chord_solve(root_finder, guess, data, memory)
        np.testing.assert_allclose(jnp.vstack(used), jnp.vstack(inverse), rtol=0, atol=MATRIX_ROUNDING)
        assert int(solution.steps) == int(fresh.steps) and int(memory.formed) == 2 and int(memory.age) == 1
    # One that serves is used as it is, also for a step size that differs by rounding;
    # its iteration runs in a loop of its own, rounded apart from the fresh one's.
    for rounded in (key, key * (1 + 4e-16)):
        good = ChordMemory(jacobian, inverse, rounded, fresh.steps, 2 * fresh.steps + 1, one * (KEPT_STEPS - 1), one)
        solution, _, used, memory = kept._chord_solve(root_finder, guess, data, good)
        np.testing.assert_array_equal(jnp.vstack(used), jnp.vstack(inverse))
        np.testing.assert_allclose(solution.value, fresh.value, rtol=0, atol=1e-15)
        assert int(memory.formed) == 1 and int(memory.age) == KEPT_STEPS
    # Not for another step size.
    other = ChordMemory(jacobian, inverse, key * 1.01, fresh.steps, fresh.steps, one, one)
    assert int(kept._chord_solve(root_finder, guess, data, other)[3].formed) == 2


def _while_loop_condition_reads(jaxpr) -> list[int]:
    """For each while loop of `jaxpr` (its sub-jaxprs too), how many elements of its
    carry its condition reads."""
    reads = []
    for equation in equations(jaxpr):
        if equation.primitive.name == "while":
            condition = equation.params["cond_jaxpr"].jaxpr
            carry = condition.invars[equation.params["cond_nconsts"] :]
            operands = [*(v for e in condition.eqns for v in e.invars), *condition.outvars]
            read = {v for v in operands if isinstance(v, Var)}
            reads.append(sum(v in read for v in carry))
    return reads


@pytest.mark.parametrize("case", list(CASES))
def test_every_while_loop_of_a_run_decides_on_two_carry_elements_or_more(case):
    """The loops of a run with a kept matrix (the steps of a save, the attempts with a
    kept and a fresh matrix, the chord iteration) each decide on at least two elements
    of their carry: XLA's search for an induction variable extracts, for a condition on
    one element, that element's whole computation in the loop's body at each run of its
    loop passes, which for the attempt loop (the chord iteration with its matrix) made
    a fifth to a third of the compile time of Euler's disk
    (`nhjax.AbstractMethod._chord_solve`). Loops over a fixed count are scans here, not
    while loops."""
    label, _, kept, h, steps = CASES[case]
    example, y0 = STARTS[label]
    jaxpr = jax.make_jaxpr(lambda y: nh.integrate(example.canonical, kept, y, h, steps, args=example.args))(y0)
    reads = _while_loop_condition_reads(jaxpr.jaxpr)
    assert len(reads) == 3 and min(reads) >= 2, reads
