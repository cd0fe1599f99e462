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


def derivative_parts(system, method, y0, dt, steps: int, repeats: int, loss_of, args=None) -> dict:
    """Where the time of a run's reverse-mode derivative goes (`nhjax._replay`), µs per
    step, timed in turns in one process: the forward run (`forward`), the recording
    scan that keeps each step's root (`record`), the replay of the steps from those
    roots without derivatives (`replay`) and with reverse mode through it
    (`replay_reverse`), which is what the derivative adds to the recording; and, per
    call inside a compiled loop at the first step's root, the step's residual
    (`residual`), its Jacobian in the unknowns by `jax.jacfwd` (`jacobian`), and the
    first step replayed from its root with one tangent of the start
    (`step_derivative`: the linearisation at the root that the derivative forms at
    every step, its Jacobian in the unknowns and along the step's data,
    `nhjax._solver.base._linearised`). `loss_of` maps the saved states to the scalar
    that is differentiated."""
    import nhjax as nh
    from nhjax import _replay

    from _timing import run_and_time_interleaved

    dt = jnp.asarray(dt)
    t0 = jnp.zeros_like(dt)

    def forward(y):
        return loss_of(nh.integrate(system, method, y, dt, steps, args=args, save_every=steps).ys)

    def record(y):
        return _replay._record(system, method, y, dt, t0, args, steps, steps)[:2]

    roots, succeeded = jax.jit(record)(y0)

    def replay(y):
        ys, _ = _replay._replayed_saves(system, method, y, dt, t0, args, roots, succeeded, steps, save_every=steps)
        return loss_of(ys)

    functions = dict(forward=jax.jit(forward), record=jax.jit(record), replay=jax.jit(replay),
                     replay_reverse=jax.jit(jax.grad(replay)))
    _, times = run_and_time_interleaved(functions, y0, repeats=repeats)
    parts = {name: seconds / steps * 1e6 for name, seconds in times.items()}

    carry = method.initial_carry(system, y0, args)
    _, data = method.setup(system, t0, dt, y0, args, carry)
    ones = jax.tree.map(jnp.ones_like, y0)

    def step_derivative(root):
        return jax.jvp(lambda y: method.replay_step(system, t0, dt, y, args, carry, root)[0], (y0,), (ones,))[1]

    parts.update(
        residual=per_call_us(lambda u: method.residual(u, data), roots[0]),
        jacobian=per_call_us(lambda u: jax.jacfwd(method.residual)(u, data), roots[0]),
        step_derivative=per_call_us(step_derivative, roots[0]),
    )
    return parts
