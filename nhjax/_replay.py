r"""Derivatives of a fixed-step run from its stored roots.

Each step of an nhjax method is a root $u_k$ of its equations $F(u, y_k) = 0$ followed
by $y_{k+1} = G(u_k, y_k)$ (`nhjax._solver.base.AbstractMethod`). A derivative of the
run needs, per step, only the linearisation of $u_k(y_k)$ by the implicit function
theorem, $\dot u_k = -(\partial_u F)^{-1}\partial_y F\,\dot y_k$, at the root; the
root finder's iterations, which diffrax's checkpointed reverse loop runs again from
every checkpoint, contribute nothing to it. So a run's derivatives come from
`replayed_run`, which `nhjax.integrate` differentiates in place of its loop
(its own derivative rule, `jax.custom_jvp`, runs the loop without derivatives and
`replayed_run` with them):

- a `lax.scan` of the method's steps without derivatives that keeps each step's root
  $u_k$ and nothing else (`AbstractMethod.solve_step`);
- a second scan that *replays* the steps from those roots
  (`AbstractMethod.replay_step`: the step's setup and completion, and $u_k$ with its
  implicit-function derivatives), whose tangent forward mode computes. Reverse mode
  transposes that tangent scan; its body is rematerialised (`jax.checkpoint`), so what
  a run stores per step is $u_k$ and the replay's state and carry, and what its
  backward pass computes per step is one replay, its linearisation and the transpose,
  never a root find.

Both scans run in chunks of a few steps (`scan_in_chunks`), so that the body of each
step's loop reads and writes a chunk's rows of the stacked roots and states, not all of
them, and XLA:CPU runs its operations one after another.

The replay repeats the recorded step's arithmetic on the same values, so its states
are the run's states; it steps to the same times $t_0 + k\,\Delta t$
(`nhjax._step_times.step_time`), reports the same codes and statistics as the run's
loop, `nhjax._fixed_steps` (a failed step is the last one taken; the saves after it
are NaN, their times inf), and a trajectory that failed has NaN derivatives
(`nhjax.integrate` gates them). `python benchmarks/gradients.py` measures the
derivative against the forward run and against diffrax's checkpointed adjoints.
"""

import jax
import jax.lax as lax
import jax.numpy as jnp

from ._chunked_scan import largest_array_bytes, scan_in_chunks, tree_bytes
from ._ledger import observe, unledgered
from ._results import RESULTS
from ._solver.base import AbstractMethod
from ._step_times import save_times, step_size, step_time
from ._system import AbstractSystem


def replay_storage_bytes(system: AbstractSystem, method: AbstractMethod, y0, args, dt, bounded: bool = False) -> int:
    """Bytes per step that a derivative through `replayed_run` keeps: the step's root
    and the replay's state and carry; for a traced number of steps within a bound
    (`bounded`), also the last step's start and root."""

    carry, root = jax.eval_shape(lambda: _first_carry_and_unknowns(system, method, y0, dt, args))
    return tree_bytes((y0, method.replayed_carry(carry), root)) * (2 if bounded else 1)


def _first_carry_and_unknowns(system, method, y0, dt, args):
    """The carry and the initial guess of a run's first step: the guess has the shape
    of every step's root. Traced for shapes only, and cheaper to trace than a whole
    step (no root find)."""
    y0 = unledgered(y0)
    carry = method.initial_carry(system, y0, args)
    return carry, method.setup(system, jnp.zeros_like(dt), dt, y0, args, carry)[0]


def _record(system, method, y_start, dt, t0, args, n_steps, max_steps):
    """The run's steps by the root finder, without derivatives: each step's root, and
    whether it was taken and succeeded, and the final method state. A failed step is
    the last one taken, as in the run's loop: the later ones are skipped, their roots
    NaN, as are those of the steps after the end (`n_steps` of `max_steps`)."""
    y_start, dt, t0, args = lax.stop_gradient((y_start, dt, t0, args))
    state = method.init(system, t0, step_time(t0, dt, jnp.array(1)), y_start, args)
    root_shape = jax.eval_shape(lambda: _first_carry_and_unknowns(system, method, y_start, dt, args)[1])

    def step(carry, k):
        y, state = carry
        h = step_size(t0, dt, k)
        running = (state.failure == RESULTS.successful) & (k < n_steps)

        def take(_):
            y1, state1, failure, root = method.solve_step(system, step_time(t0, dt, k), h, y, args, state)
            failed = failure != RESULTS.successful
            y1 = jax.tree.map(lambda x: jnp.where(failed, jnp.nan, x), y1)
            return (y1, state1), (root, ~failed)

        def skip(_):
            root = jnp.full(root_shape.shape, jnp.nan, root_shape.dtype)
            return (y, state), (root, jnp.array(False))

        (y1, state1), (root, succeeded) = lax.cond(running, take, skip, None)
        return (y1, state1), (root, succeeded, running)

    # A step's rows: its index and its root (and two one-byte flags).
    row_bytes = largest_array_bytes((jnp.arange(1), root_shape))
    (_, final_state), (roots, succeeded, taken) = scan_in_chunks(
        step, (y_start, state), jnp.arange(max_steps), row_bytes
    )
    return roots, succeeded, taken, final_state


def _replayed_saves(system, method, y_start, dt, t0, args, roots, succeeded, n_steps, *, save_every):
    """The saved states and observables of the run replayed from its roots (with the
    derivatives of `AbstractMethod.replay_step`).

    A step after the end holds the state. It replays the last step of the run again,
    from that step's own start and root, and discards the result: a replay from a
    skipped step's NaN root would give the discarded branch NaN derivatives, which
    reverse mode multiplies by the zero cotangent of the branch not taken (under
    `vmap`, where the steps of a batch end at different `n_steps`)."""
    carry = method.replayed_carry(method.initial_carry(system, unledgered(y_start), args))
    n_saves = roots.shape[0] // save_every
    save = observe(system)

    @jax.checkpoint
    def step(state, inputs):
        y, carry, last = state
        k, root, success = inputs
        if isinstance(n_steps, int):  # static: every step is in the run
            y1, carry1 = method.replay_step(system, step_time(t0, dt, k), step_size(t0, dt, k), y, args, carry, root)
            y1 = jax.tree.map(lambda x: jnp.where(success, x, jnp.nan), y1)
            return (y1, carry1, last), None
        in_run = k < n_steps
        replayed = jax.tree.map(lambda new, old: jnp.where(in_run, new, old), (y, carry, root, k), last)
        y_k, carry_k, root_k, index = replayed
        y1, carry1 = method.replay_step(
            system, step_time(t0, dt, index), step_size(t0, dt, index), y_k, args, carry_k, root_k
        )
        y1 = jax.tree.map(lambda x: jnp.where(success, x, jnp.nan), y1)
        y1, carry1 = jax.tree.map(lambda new, old: jnp.where(in_run, new, old), (y1, carry1), (y, carry))
        return (y1, carry1, replayed), None

    first_step = None if isinstance(n_steps, int) else (y_start, carry, roots[0], jnp.array(0))
    start = (y_start, carry, first_step)
    # A step's rows: its inputs, and in reverse mode the state it starts from, kept for
    # the backward pass.
    step_bytes = largest_array_bytes((start, jnp.arange(1), roots[0]))

    def between_saves(state, inputs):
        state, _ = scan_in_chunks(step, state, inputs, step_bytes)
        return state, save(None, state[0], args)

    blocks = jax.tree.map(
        lambda x: x.reshape(n_saves, save_every, *x.shape[1:]),
        (jnp.arange(roots.shape[0]), roots, succeeded),
    )
    first = save(None, y_start, args)
    # A block's rows: its steps' inputs, the state it starts from, and its save.
    block_bytes = max(
        save_every * largest_array_bytes((jnp.arange(1), roots[0])), largest_array_bytes((start, first))
    )
    _, (ys, observed) = scan_in_chunks(between_saves, start, blocks, block_bytes)
    first = jax.tree.map(lambda x: x[None], first)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b]), first, (ys, observed))


def replayed_run(system, method, y_start, dt, t0, args, n_steps, *, max_steps: int, save_every: int):
    """The run of `n_steps` fixed steps, saved as a run of `max_steps`, as
    `nhjax.integrate`'s loop returns it, `(ts, (ys, observed), final method
    state, the run's code, number of steps taken)`, computed for derivatives: the steps
    by the root finder without derivatives (`_record`), then the saves of the steps
    replayed from their roots, which carry the derivatives (see the module docstring)."""
    roots, succeeded, taken, final_state = _record(system, method, y_start, dt, t0, args, n_steps, max_steps)
    ts = save_times(t0, dt, n_steps, max_steps // save_every, save_every=save_every)
    saved = _replayed_saves(
        system, method, y_start, dt, t0, args, roots, succeeded, n_steps, save_every=save_every
    )
    # The run's code from the method's state, as the run's loop reports it (a step
    # that fails is the loop's only way to stop early).
    return ts, saved, final_state, final_state.failure, jnp.sum(taken, dtype=int)
