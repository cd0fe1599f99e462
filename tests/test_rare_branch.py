"""`rarely`: the branch's value where taken, the common value elsewhere, and under vmap
the branch evaluated only at the steps where some trajectory takes it."""

import jax
import jax.numpy as jnp
import numpy as np

import nhjax._rare_branch
from nhjax._rare_branch import rarely


def _counting(calls):
    """x -> (sin(x) * scale, 2 scale), recording each evaluation (batched or not)."""

    def rare(operands):
        x, scale = operands
        jax.debug.callback(lambda: calls.append(1))
        return jnp.sin(x) * scale, 2 * scale

    return rare


def test_one_trajectory_takes_its_own_branch():
    calls = []
    rare = _counting(calls)
    common = (jnp.zeros(3), jnp.asarray(-1.0))
    x = jnp.array([0.1, 0.2, 0.3])
    taken = jax.jit(lambda x: rarely(jnp.asarray(True), rare, common, (x, jnp.asarray(3.0))))(x)
    np.testing.assert_allclose(taken[0], 3 * jnp.sin(x), rtol=1e-15)
    assert float(taken[1]) == 6.0
    skipped = jax.jit(lambda x: rarely(jnp.asarray(False), rare, common, (x, jnp.asarray(3.0))))(x)
    assert float(jnp.max(jnp.abs(skipped[0]))) == 0.0 and float(skipped[1]) == -1.0
    jax.effects_barrier()
    assert len(calls) == 1


def test_under_vmap_each_member_gets_its_branch_and_the_branch_runs_only_when_needed():
    calls = []
    rare = _counting(calls)
    xs = jnp.linspace(0.1, 0.8, 12).reshape(4, 3)
    common = (-xs, -jnp.ones(4))

    def batch(taken):
        # The scale is shared by the batch (not batched), the points are not.
        return jax.vmap(lambda t, x, c: rarely(t, rare, c, (x, jnp.asarray(3.0))))(taken, xs, common)

    batch = jax.jit(batch)
    some = jnp.array([False, True, False, True])
    values, scales = batch(some)
    jax.effects_barrier()
    assert len(calls) == 1  # once, batched
    np.testing.assert_allclose(values, jnp.where(some[:, None], 3 * jnp.sin(xs), -xs), rtol=1e-15)
    np.testing.assert_array_equal(scales, jnp.where(some, 6.0, -1.0))

    values, scales = batch(jnp.zeros(4, dtype=bool))
    jax.effects_barrier()
    assert len(calls) == 1  # no member takes it: not evaluated
    np.testing.assert_array_equal(values, -xs)
    np.testing.assert_array_equal(scales, -jnp.ones(4))


def test_evaluating_both_branches_selects_the_same_values_without_a_conditional(monkeypatch):
    """With `EVALUATE_BOTH_BRANCHES` (set before tracing) every call evaluates the rare
    branch and selects: the same values, alone and under vmap, and no `conditional` in
    the compiled program."""
    xs = jnp.linspace(0.1, 0.8, 12).reshape(4, 3)
    some = jnp.array([False, True, False, True])

    def batch(taken):
        rare = lambda operands: (jnp.sin(operands[0]) * operands[1], 2 * operands[1])  # noqa: E731
        return jax.vmap(lambda t, x, c: rarely(t, rare, c, (x, jnp.asarray(3.0))))(taken, xs, (-xs, -jnp.ones(4)))

    with_cond = jax.jit(batch)
    expected = with_cond(some)
    assert "conditional(" in with_cond.lower(some).compile().as_text()
    monkeypatch.setattr(nhjax._rare_branch, "EVALUATE_BOTH_BRANCHES", True)
    selected = jax.jit(lambda taken: batch(taken))
    for got, want in zip(selected(some), expected):
        np.testing.assert_array_equal(got, want)
    assert "conditional(" not in selected.lower(some).compile().as_text()
    alone = jax.jit(lambda x: rarely(jnp.asarray(True), lambda o: jnp.sin(o), -x, x))(xs[0])
    np.testing.assert_array_equal(alone, jnp.sin(xs[0]))
