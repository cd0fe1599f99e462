r"""The fixed-step runs' step times: $t_k = t_0 + k\,\Delta t$, each computed from $k$ as
`t0 + dt * k`, by every loop that strings fixed steps together."""

import diffrax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


def step_time(t0: Float[Array, ""], dt: Float[Array, ""], k: Int[Array, "*steps"]) -> Float[Array, "*steps"]:
    """$t_k$, rounded as `t0 + dt * jnp.arange(n + 1)` rounds it."""
    return t0 + dt * k.astype(dt.dtype)


def step_size(t0: Float[Array, ""], dt: Float[Array, ""], k: Int[Array, ""]) -> Float[Array, ""]:
    """$h_k = t_{k+1} - t_k$, the step a loop hands the method (diffrax's loop as the
    difference of the step's times)."""
    return step_time(t0, dt, k + 1) - step_time(t0, dt, k)


def save_times(t0: Float[Array, ""], dt: Float[Array, ""], n_steps, n_saves: int, *, save_every: int) -> Float[Array, " n_saves+1"]:
    """The save times $t_{\\min(i s, n)}$, $i = 0, \\dots$, `n_saves` ($s$ =
    `save_every`, $n$ = `n_steps`) of a fixed-step run saved as a run of
    `n_saves * save_every` steps."""
    steps = jnp.minimum(save_every * jnp.arange(n_saves + 1), n_steps)
    return step_time(t0, dt, steps)


class FixedStepTimes(diffrax.AbstractStepSizeController):
    r"""diffrax's loop stepping to exactly $t_k$ (`step_time`).

    What `diffrax.StepTo` does with the array of all step times, without reading that
    array in the loop, which on XLA:CPU slowed every step of a cheap method by a large
    fraction of its cost (the times and states are identical;
    `python benchmarks/gonzalez_r.py` measures the loop's cost per step against a bare
    `lax.scan` of the same steps). The run ends when
    diffrax's loop reaches $t_1 = t_0 + n\,\Delta t$; `integrate` checks beforehand that
    no step lands within diffrax's end-clipping margin (100 ulps) of t1 early."""

    t0: Float[Array, ""]
    dt: Float[Array, ""]

    def wrap(self, direction):
        del direction  # integrate always steps forward
        return self

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        del terms, t0, t1, y0, dt0, args, func, error_order
        return step_time(self.t0, self.dt, jnp.array(1)), jnp.array(2, dtype=jnp.int32)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        del t0, y0, y1_candidate, args, y_error, error_order
        k = controller_state
        return True, t1, step_time(self.t0, self.dt, k), False, k + 1, diffrax.RESULTS.successful
