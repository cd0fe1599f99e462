"""A branch that few steps take, kept rare under `jax.vmap`.

Under `vmap` a `lax.cond` whose predicate differs between trajectories becomes a
select: every trajectory evaluates both branches at every step. `rarely` batches its
branch by hand (`jax.custom_batching.custom_vmap`): the batch evaluates the rare branch
only at the steps where some trajectory takes it."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array, Bool, PyTree


# Read when a function is traced: `rarely` then evaluates the rare branch at every call
# and selects, with no `lax.cond`. On a GPU a `lax.cond` copies its predicate to the
# host, which can cost more than a small branch; `benchmarks/gpu.py` sets it in a child
# process to measure that. Off everywhere else.
EVALUATE_BOTH_BRANCHES = False


def rarely(taken: Bool[Array, ""], rare: Callable[[PyTree], PyTree], common: PyTree, operands: PyTree) -> PyTree:
    """`rare(operands)` where `taken`, else `common` (`rare` returns arrays of the same
    structure, shapes and dtypes).

    A `lax.cond` for one trajectory. Under `vmap`, `rare` runs, batched over the whole
    batch, at a step only when some trajectory takes it, and each trajectory gets its
    own branch's value. Not differentiable: the caller passes inputs cut from
    differentiation (`lax.stop_gradient`), whose tangents are zero, so that no
    derivative of this function is ever formed."""
    if EVALUATE_BOTH_BRANCHES:
        return jax.tree.map(lambda value, other: jnp.where(taken, value, other), rare(operands), common)
    dynamic, static = eqx.partition(operands, eqx.is_array)

    def evaluate(dynamic):
        return rare(eqx.combine(dynamic, static))

    @jax.custom_batching.custom_vmap
    def select(taken, common, dynamic):
        return lax.cond(taken, lambda: evaluate(dynamic), lambda: common)

    @select.def_vmap
    def _select_batched(axis_size, in_batched, taken, common, dynamic):
        taken_batched, common_batched, dynamic_batched = in_batched

        def batched(x, is_batched):
            return x if is_batched else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))

        taken = batched(taken, taken_batched)
        common = jax.tree.map(batched, common, common_batched)
        in_axes = jax.tree.map(lambda is_batched: 0 if is_batched else None, dynamic_batched)

        def evaluate_batch():
            values = jax.vmap(evaluate, in_axes=(in_axes,))(dynamic)
            return jax.tree.map(
                lambda value, other: jnp.where(taken.reshape((axis_size,) + (1,) * (value.ndim - 1)), value, other),
                values,
                common,
            )

        result = lax.cond(jnp.any(taken), evaluate_batch, lambda: common)
        return result, jax.tree.map(lambda _: True, common)

    return select(taken, common, dynamic)
