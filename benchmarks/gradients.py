"""Derivatives through long GONZALEZ-R runs on the gearbox: their compile time, their
time against the forward run's, and peak memory.

The loss is a smooth function of the final state after N steps at h = 0.1, for each N in
`--steps` (default 2 000 and 100 000), differentiated with respect to the initial state
(q0, p0) through `nhjax.integrate`. Modes: `reverse` (`jax.grad`) and `forward-mode`
(`jax.jacfwd`) with the default adjoint (the steps replayed from their stored roots,
`nhjax._replay`); for comparison, `reverse-checkpointed` with diffrax's loop
checkpointed at every step (`diffrax.RecursiveCheckpointAdjoint(checkpoints=N)`, the
default before the replay), `reverse-log-checkpoints` with its O(log n) checkpoints,
and `forward-mode-diffrax` (`diffrax.ForwardMode()`). Each measurement runs in its own
process, so that its peak resident memory (`ru_maxrss`) is its own; the peak after
compilation is recorded too, so that what the run itself adds is visible. A
derivative's time ratio to the forward run comes from its own process, the two timed in
turn after the memory is recorded.

Run: python benchmarks/gradients.py [--steps N ...] [--repeats R]
Medians over repeats; results go to benchmarks/results/gradients.json.
"""

import argparse
import json
import pathlib
import resource
import subprocess
import sys


_MODES = (
    "forward",
    "reverse",
    "forward-mode",
    "reverse-checkpointed",
    "reverse-log-checkpoints",
    "forward-mode-diffrax",
)


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def measure(mode: str, steps: int, repeats: int) -> dict:
    """In this process: compile and time the forward run or its gradient."""
    import diffrax
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import nhjax as nh
    from _timing import run_and_time, run_and_time_interleaved, timed

    gearbox = nh.examples.gearbox()
    y0 = gearbox.random_initial_state(jax.random.key(0))
    # Each mode: the adjoint (None: nhjax's default) and what is taken of the loss.
    adjoint, transform = {
        "forward": (None, lambda function: function),
        "reverse": (None, jax.grad),
        "forward-mode": (None, jax.jacfwd),
        "reverse-checkpointed": (diffrax.RecursiveCheckpointAdjoint(checkpoints=steps), jax.grad),
        "reverse-log-checkpoints": (diffrax.RecursiveCheckpointAdjoint(), jax.grad),
        "forward-mode-diffrax": (diffrax.ForwardMode(), jax.jacfwd),
    }[mode]

    def loss(y0):
        solution = nh.integrate(
            gearbox.canonical, nh.GonzalezR(), y0, 0.1, steps, save_every=steps, adjoint=adjoint
        )
        q, p = solution.ys
        return jnp.sum(q[-1] ** 2) + jnp.sum(jnp.cos(p[-1]))

    function = jax.jit(transform(loss))
    compile_s = timed(lambda y: function.lower(y).compile(), y0)
    compiled_peak = _peak_mib()
    value, seconds = run_and_time(function, y0, repeats=repeats)
    finite = all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(value))
    result = dict(
        seconds=seconds,
        compile_s=compile_s,
        peak_after_compile_mib=compiled_peak,
        peak_mib=_peak_mib(),
        finite=finite,
    )
    if mode != "forward":
        # The time ratio from this process, the forward run timed in turn with the
        # derivative, so that the machine's drift falls on both alike.
        _, times = run_and_time_interleaved(dict(derivative=function, forward=jax.jit(loss)), y0, repeats=repeats)
        result["time_ratio_to_forward"] = times["derivative"] / times["forward"]
    return result


def _in_subprocess(mode: str, steps: int, repeats: int) -> dict:
    command = [sys.executable, __file__, "--child", mode, "--steps", str(steps), "--repeats", str(repeats)]
    output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, nargs="+", default=[2_000, 100_000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--child", choices=_MODES)
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "gradients.json"))
    options = parser.parse_args()
    if options.child:
        print(json.dumps(measure(options.child, options.steps[0], options.repeats)))
        return

    from _timing import write

    results = dict(dt=0.1, runs={})
    for steps in options.steps:
        run = {}
        for mode in _MODES:
            run[mode] = _in_subprocess(mode, steps, options.repeats)
            print(f"{steps} steps, {mode}: {run[mode]}", flush=True)
        results["runs"][str(steps)] = run
    write(results, options.out)


if __name__ == "__main__":
    main()
