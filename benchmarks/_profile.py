"""Where a root-find step's time goes: each part of one step of an nhjax method, timed
alone inside a compiled loop (so that dispatch overhead does not count), beside the
measured cost of whole steps."""

import time

import jax
import jax.lax as lax
import jax.numpy as jnp

from nhjax._solver.base import AbstractMethod
from nhjax._solver.chord import chord_inverse


def per_call_us(function, x, repeats: int = 200) -> float:
    """µs per call of `function(x)`, from a `lax.scan` of `repeats` calls; each call's
    input depends on the previous output, so the compiler can neither hoist nor drop it."""

    @jax.jit
    def loop(offset):
        def body(offset, _):
            out = function(x + offset)
            total = sum(jnp.sum(leaf) for leaf in jax.tree.leaves(out))
            return offset + 1e-300 * total, None

        return lax.scan(body, offset, None, length=repeats)[0]

    zero = jnp.zeros((), x.dtype)
    jax.block_until_ready(loop(zero))
    start = time.perf_counter()
    jax.block_until_ready(loop(zero))
    return (time.perf_counter() - start) / repeats * 1e6


def step_parts(system, method, y0, h, iterations: float, args=None, repeats: int = 200) -> dict:
    """µs of each part of one step of `method` (an `nhjax.AbstractMethod`) from `y0`:
    `setup` (state to unknowns, predictor), `chord_matrix` (the method's Jacobian of the
    simplified residual at the guess, and its inverse, as the method forms them
    (`AbstractMethod.chord_matrix`): once per step), `residual` (once
    per root-finder iteration) and `complete` (unknowns to the new state). `model` is
    setup + chord_matrix + iterations x residual + complete. For a method with its own
    `chord_jacobian`, `chord_matrix_by_jacfwd` is the generic `jax.jacfwd` it replaces."""
    carry = method.initial_carry(system, y0, args)
    guess, data = method.setup(system, 0.0, h, y0, args, carry)
    q_or_x = jax.tree.leaves(y0)[0]

    def setup(offset):
        shifted = jax.tree.map(lambda leaf: leaf + offset[0], y0)
        return method.setup(system, 0.0, h, shifted, args, carry)[0]

    parts = dict(
        setup=per_call_us(setup, jnp.zeros((1,), q_or_x.dtype), repeats),
        chord_matrix=per_call_us(lambda u: method.chord_matrix(u, data), guess, repeats),
        residual=per_call_us(lambda u: method.residual(u, data), guess, repeats),
        complete=per_call_us(lambda u: jax.tree.leaves(method.complete(u, data)[0]), guess, repeats),
    )
    if type(method).chord_jacobian is not AbstractMethod.chord_jacobian:
        # The method's own chord Jacobian against the generic one it replaces.
        parts["chord_matrix_by_jacfwd"] = per_call_us(
            lambda u: chord_inverse(jax.jacfwd(method.simplified_residual)(u, data)), guess, repeats
        )
    parts["model"] = (
        parts["setup"] + parts["chord_matrix"] + iterations * parts["residual"] + parts["complete"]
    )
    return parts
