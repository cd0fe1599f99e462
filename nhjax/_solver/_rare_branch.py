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


def rarely(
    taken: Bool[Array, ""], rare: Callable[[PyTree], PyTree], common: PyTree | Callable[[PyTree], PyTree], operands: PyTree
) -> PyTree:
    """`rare(operands)` where `taken`, else `common`: a value, or a function evaluated
    as `common(operands)` (`rare` and `common` return arrays of the same structure,
    shapes and dtypes).

    A `lax.cond` for one trajectory, which evaluates only the branch taken. Under
    `vmap`, `rare` runs, batched over the whole batch, at a step only when some
    trajectory takes it, a function `common` for the whole batch at every step, and
    each trajectory gets its own branch's value. Not differentiable: the caller passes
    inputs cut from differentiation (`lax.stop_gradient`), whose tangents are zero, so
    that no derivative of this function is ever formed."""
    dynamic, static = eqx.partition(operands, eqx.is_array)

    def evaluate(function, dynamic):
        return function(eqx.combine(dynamic, static))

    def choose_batched(axis_size, taken, common, dynamic, dynamic_batched):
        in_axes = jax.tree.map(lambda is_batched: 0 if is_batched else None, dynamic_batched)

        def evaluate_batch():
            values = jax.vmap(lambda d: evaluate(rare, d), in_axes=(in_axes,), axis_size=axis_size)(dynamic)
            return jax.tree.map(
                lambda value, other: jnp.where(taken.reshape((axis_size,) + (1,) * (value.ndim - 1)), value, other),
                values,
                common,
            )

        result = lax.cond(jnp.any(taken), evaluate_batch, lambda: common)
        return result, jax.tree.map(lambda _: True, common)

    def batched(x, is_batched, axis_size):
        return x if is_batched else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))

    if callable(common):
        common_function = common

        @jax.custom_batching.custom_vmap
        def select_lazily(taken, dynamic):
            return lax.cond(taken, lambda: evaluate(rare, dynamic), lambda: evaluate(common_function, dynamic))

        @select_lazily.def_vmap
        def _select_lazily_batched(axis_size, in_batched, taken, dynamic):
            taken_batched, dynamic_batched = in_batched
            in_axes = jax.tree.map(lambda is_batched: 0 if is_batched else None, dynamic_batched)
            values = jax.vmap(lambda d: evaluate(common_function, d), in_axes=(in_axes,), axis_size=axis_size)(dynamic)
            return choose_batched(axis_size, batched(taken, taken_batched, axis_size), values, dynamic, dynamic_batched)

        return select_lazily(taken, dynamic)

    @jax.custom_batching.custom_vmap
    def select(taken, common, dynamic):
        return lax.cond(taken, lambda: evaluate(rare, dynamic), lambda: common)

    @select.def_vmap
    def _select_batched(axis_size, in_batched, taken, common, dynamic):
        taken_batched, common_batched, dynamic_batched = in_batched
        common = jax.tree.map(lambda x, is_batched: batched(x, is_batched, axis_size), common, common_batched)
        return choose_batched(axis_size, batched(taken, taken_batched, axis_size), common, dynamic, dynamic_batched)

    return select(taken, common, dynamic)
