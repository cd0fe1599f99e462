"""The fixed-step runs' step-size controller."""

import diffrax
import jax.numpy as jnp
from jaxtyping import Array, Float


class FixedStepTimes(diffrax.AbstractStepSizeController):
    r"""Steps to exactly $t_k = t_0 + k\,\Delta t$, $k = 1, \dots$, each time computed from
    $k$ as `t0 + dt * k` (the same rounding as `t0 + dt * jnp.arange(n + 1)`).

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
        return self.t0 + self.dt, jnp.array(2, dtype=jnp.int32)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        del t0, y0, y1_candidate, args, y_error, error_order
        k = controller_state
        next_time = self.t0 + self.dt * k.astype(self.dt.dtype)
        return True, t1, next_time, False, k + 1, diffrax.RESULTS.successful
