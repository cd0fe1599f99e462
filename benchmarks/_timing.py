"""What the benchmark scripts share: their command-line options, wall-clock timing of
JAX calls, the machine's description, and writing the results."""

import argparse
import json
import os
import pathlib
import platform
import statistics
import time
from typing import Any

import jax


def options(description: str, result: str, **defaults) -> argparse.Namespace:
    """The command line: `--name` for each of `defaults` (`--batch-steps` for
    `batch_steps`), of its default's type (a switch where the default is `False`), and
    `--out`, the JSON file, by default `results/<result>.json` beside the scripts."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    for name, default in defaults.items():
        if default is False:
            parser.add_argument("--" + name.replace("_", "-"), action="store_true")
        else:
            parser.add_argument("--" + name.replace("_", "-"), type=type(default), default=default)
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / f"{result}.json"))
    return parser.parse_args()


# XLA:CPU's loop emitter in place of its default MLIR fusion emitters, for one
# compilation: what the `nhjax` command and the test suite set for their processes by
# `XLA_FLAGS`, and what a user may pass to `jax.jit(..., compiler_options=...)`.
LOOP_EMITTER = {"xla_cpu_use_fusion_emitters": False}


def timed(function, *arguments) -> float:
    """Seconds for `function(*arguments)`, waiting for JAX's asynchronous dispatch."""
    start = time.perf_counter()
    jax.block_until_ready(function(*arguments))
    return time.perf_counter() - start


class CompileTimes:
    """The seconds before a jitted `function`'s first run on `arguments`: tracing and
    lowering (`trace_and_lower_s`, timed on construction), plus XLA's compilation with
    its default emitters (`compile_s`, also on construction), plus, of the same lowered
    program, with its loop emitter (`loop_emitter_compile_s`, `LOOP_EMITTER`, timed by
    `times()`, which a caller may put after its memory figures). Also the size of the
    program XLA compiled, in lines of its optimised HLO (`hlo_lines`): unlike the
    times, the same on every run of one JAX version, so that a change in a program's
    size shows through this machine's noise."""

    def __init__(self, function, *arguments):
        start = time.perf_counter()
        self.lowered = function.lower(*arguments)
        self.trace_and_lower_s = time.perf_counter() - start
        start = time.perf_counter()
        compiled = self.lowered.compile()
        self.compile_s = self.trace_and_lower_s + time.perf_counter() - start
        self.hlo_lines = len(compiled.as_text().splitlines())

    def times(self) -> dict[str, float]:
        loop_emitter_s = timed(lambda: self.lowered.compile(compiler_options=LOOP_EMITTER))
        return dict(
            compile_s=self.compile_s,
            trace_and_lower_s=self.trace_and_lower_s,
            loop_emitter_compile_s=self.trace_and_lower_s + loop_emitter_s,
            hlo_lines=self.hlo_lines,
        )


def run_and_time(function, *arguments, repeats: int) -> tuple[Any, float]:
    """The output of a first, untimed call of `function(*arguments)`, which also warms
    it up, and the median seconds of `repeats` timed calls after it."""
    output = jax.block_until_ready(function(*arguments))
    return output, statistics.median(timed(function, *arguments) for _ in range(repeats))


def run_and_time_interleaved(functions: dict, *arguments, repeats: int) -> tuple[dict, dict]:
    """`run_and_time` for several functions on the same `arguments`, the timed calls
    taken in turn (A, B, C, A, B, C, ...) so that the machine's drift falls on all
    alike: ({name: output}, {name: median seconds})."""
    outputs = {name: jax.block_until_ready(function(*arguments)) for name, function in functions.items()}
    times = {name: [] for name in functions}
    for _ in range(repeats):
        for name, function in functions.items():
            times[name].append(timed(function, *arguments))
    return outputs, {name: statistics.median(seconds) for name, seconds in times.items()}


def machine() -> dict:
    """The processor, JAX's devices and backend, and `XLA_FLAGS` as the process has
    it: XLA's flags change both run and compile times (the README's performance
    paragraphs), so a result names those it was measured under."""
    return dict(
        processor=platform.processor(),
        cpus=jax.local_device_count(),
        backend=jax.default_backend(),
        xla_flags=os.environ.get("XLA_FLAGS", ""),
    )


def write(results: dict, path: str) -> None:
    out = pathlib.Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(results, machine=machine(), jax=jax.__version__), indent=2))
    print(f"wrote {out}")


def per_step(system, method, y0, steps, repeats, args=None, dt=0.1):
    """(median µs/step, compile s, root-finder iterations/step or None) for one
    trajectory of `steps` steps of `method` through `nhjax.integrate`."""
    import nhjax as nh

    run = jax.jit(lambda y0: nh.integrate(system, method, y0, dt, steps, args=args, save_every=steps))
    compile_s = timed(lambda y: run.lower(y).compile(), y0)
    solution, seconds = run_and_time(run, y0, repeats=repeats)
    total = solution.stats["root_find_steps"]
    iterations = None if total is None else float(total) / steps
    return seconds / steps * 1e6, compile_s, iterations


def bare_loop(system, method, steps, args=None, dt=0.1):
    """A run of `steps` steps of `method` strung together by a bare `lax.scan` of the
    method's step (`method.advance`), without `nhjax.integrate`'s loop: a function of the start
    that returns the final state."""
    import jax.numpy as jnp

    def run(y0):
        state = method.init(system, 0.0, dt, y0, args)
        h = jnp.asarray(dt, jax.tree.leaves(y0)[0].dtype)

        def step(carry, _):
            y, state = carry
            # Conservative systems: the step's time is not read.
            y, state, _ = method.advance(system, jnp.zeros_like(h), h, y, args, state)
            return (y, state), None

        return jax.lax.scan(step, (y0, state), None, length=steps)[0][0]

    return run


def bare_loop_per_step(system, method, y0, steps, repeats, args=None, dt=0.1) -> float:
    """Median µs/step of the same steps as `per_step` strung together by `bare_loop`:
    what `nhjax.integrate`'s loop costs is the difference."""
    _, seconds = run_and_time(jax.jit(bare_loop(system, method, steps, args, dt)), y0, repeats=repeats)
    return seconds / steps * 1e6


def bare_loop_batch_rate(system, method, states, steps, repeats, args=None, dt=0.1) -> float:
    """Median trajectory-steps/s of `bare_loop` vmapped over the leading axis of
    `states`, as `batch_rate` for `nhjax.integrate`."""
    run = jax.jit(jax.vmap(bare_loop(system, method, steps, args, dt)))
    _, seconds = run_and_time(run, states, repeats=repeats)
    return jax.tree.leaves(states)[0].shape[0] * steps / seconds


def batch_rate(system, method, states, steps, repeats, args=None, dt=0.1):
    """(median trajectory-steps/s, number of failed trajectories) of a vmapped batch
    (leading axis of `states`), run with `throw=False` so that a failure is counted,
    not raised."""
    import nhjax as nh

    run = jax.jit(jax.vmap(
        lambda y0: nh.integrate(system, method, y0, dt, steps, args=args, save_every=steps, throw=False).result
    ))
    results, seconds = run_and_time(run, states, repeats=repeats)
    failed = int(jax.numpy.sum(results != nh.RESULTS.successful))
    size = jax.tree.leaves(states)[0].shape[0]
    return size * steps / seconds, failed


def _yardstick_field(y):
    q, p = y[:3], y[3:]
    return jax.numpy.concatenate([p, -jax.numpy.sin(q) - 0.1 * (q - jax.numpy.roll(q, 1))])


def _yardstick_run(y0, steps, h=0.1):
    jnp = jax.numpy

    def step(y, _):
        def newton(z, _):
            def residual(z):
                return z - y - h * _yardstick_field(0.5 * (y + z))

            return z - jnp.linalg.solve(jax.jacfwd(residual)(z), residual(z)), None

        z, _ = jax.lax.scan(newton, y, None, length=3)
        return z, None

    y1, _ = jax.lax.scan(step, y0, None, length=steps)
    return y1


def yardstick_states(batch=None):
    """Initial states of the implicit-midpoint yardstick: one, or `batch` of them."""
    jnp = jax.numpy
    y0 = jnp.array([0.3, -0.2, 0.5, 0.1, 0.4, -0.3])
    if batch is None:
        return y0
    return y0 + 0.1 * jax.random.normal(jax.random.key(2), (batch, 6), dtype=y0.dtype)


def yardstick(steps, repeats, batch=None):
    """The implicit-midpoint yardstick: $y' = y + h f((y + y')/2)$ on $\\mathbb{R}^6$,
    $f = (p, -\\sin q - 0.1(q - \\mathrm{roll}(q, 1)))$, $h = 0.1$, three Newton
    iterations per step (`jax.jacfwd`, `jnp.linalg.solve`), one `lax.scan`: median
    µs/step for one trajectory, or trajectory-steps/s for a vmapped batch of `batch`."""
    run = jax.jit(lambda y0: _yardstick_run(y0, steps))
    if batch is None:
        _, seconds = run_and_time(run, yardstick_states(), repeats=repeats)
        return seconds / steps * 1e6
    run = jax.jit(jax.vmap(lambda y0: _yardstick_run(y0, steps)))
    _, seconds = run_and_time(run, yardstick_states(batch), repeats=repeats)
    return batch * steps / seconds
