"""What the benchmark scripts share: wall-clock timing of JAX calls, the machine's
description, and writing the results."""

import json
import pathlib
import platform
import statistics
import time
from typing import Any

import jax


def timed(function, *arguments) -> float:
    """Seconds for `function(*arguments)`, waiting for JAX's asynchronous dispatch."""
    start = time.perf_counter()
    jax.block_until_ready(function(*arguments))
    return time.perf_counter() - start


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
    return dict(processor=platform.processor(), cpus=jax.local_device_count(), backend=jax.default_backend())


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
