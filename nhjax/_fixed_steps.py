r"""nhjax's own loop of fixed steps: the run that `nhjax.integrate` returns when nothing
differentiates through its loop.

`diffrax.diffeqsolve` strings any steps together, with adaptive step sizes, dense
output, events, progress meters and adjoints; a fixed-step run needs none of that
except an adjoint, and `nhjax.integrate` differentiates its runs by its own rule
(`nhjax._replay`, or diffrax's loop inside the rule). What the general loop costs such a
run is compile time: its end-time clipping alone (t1 taken back 100 ulps one
`prevbefore` at a time, on a traced t1) is some 1 700 HLO instructions in every
program, and its bookkeeping for saves, jumps and events as much again. This loop is a
`lax.scan` over blocks of `save_every` steps, saving after each block, each block a
`lax.while_loop` of the solver's steps (`diffrax.AbstractSolver.step`, any solver) that
stops at the run's end or at a failure, with the same step times (`step_time`), the
same codes and statistics, and the same saves as diffrax's loop with
`nhjax._step_times.FixedStepTimes`: a step that fails is the last one taken, and the
steps after it, or after `n_steps` of a run bounded by `max_steps`, keep the state
(`nhjax._integrate` fills the saves after a failure as diffrax does).
"""

import diffrax
import jax.lax as lax
import jax.numpy as jnp

from ._ledger import observe
from ._results import first_failure, from_diffrax, RESULTS
from ._solution import method_outcome
from ._step_times import save_times, step_time


def fixed_step_run(system, method: diffrax.AbstractSolver, y_start, dt, t0, args, n_steps, *, max_steps: int, save_every: int):
    """The run of `n_steps` fixed steps of `method` from `y_start`, saved as a run of
    `max_steps`: `(ts, (ys, observed), final solver state, the run's code, number of
    steps taken)`, as `nhjax._integrate`'s diffrax loop returns it. Not differentiable
    through the loop's control (a failure stops it), as diffrax's loop would be with
    an adjoint: `nhjax.integrate` differentiates it by its own rule."""
    save = observe(system)
    state = method.init(system, t0, step_time(t0, dt, jnp.array(1)), y_start, args)

    def step(carry):
        k, y, state, _ = carry
        y1, _, _, state1, result = method.step(system, step_time(t0, dt, k), step_time(t0, dt, k + 1), y, args, state, False)
        return k + 1, y1, state1, from_diffrax(result)

    def block(carry, end):
        # A while loop, not a scan, within the block: a run bounded by `max_steps`
        # stops at its `n_steps`, and the blocks after it cost one save each.
        running = lambda carry: (carry[0] < jnp.minimum(end, n_steps)) & (carry[3] == RESULTS.successful)  # noqa: E731
        carry = lax.while_loop(running, step, carry)
        return carry, save(None, carry[1], args)

    n_saves = max_steps // save_every
    start = (jnp.array(0), y_start, state, RESULTS.successful)
    # The first block has no steps: it saves the start, so that the saves are traced once.
    (taken, _, final_state, code), saved = lax.scan(block, start, save_every * jnp.arange(n_saves + 1))
    method_failure, _ = method_outcome(final_state)
    ts = save_times(t0, dt, n_steps, n_saves, save_every=save_every)
    return ts, saved, final_state, first_failure(method_failure, code), taken
