"""Reverse-mode gradients through long GONZALEZ-R runs on the gearbox: peak memory and
the time of a gradient against the time of the forward run.

The loss is a smooth function of the final state after `--steps` steps at h = 0.1
(default 100 000), differentiated with respect to the initial state (q0, p0) with
`jax.grad` through `nhjax.integrate` and its default adjoint,
`diffrax.RecursiveCheckpointAdjoint()` (O(log n) checkpoints), and with a fixed number
of checkpoints for comparison. Each measurement runs in its own process, so that its
peak resident memory (`ru_maxrss`) is its own; the peak after compilation is recorded
too, so that what the run itself adds is visible.

Run: python benchmarks/gradients.py [--steps N] [--repeats R]
Medians over repeats; results go to benchmarks/results/gradients.json.
"""

import argparse
import json
import pathlib
import resource
import subprocess
import sys


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def measure(mode: str, steps: int, repeats: int, checkpoints: int | None) -> dict:
    """In this process: compile and time the forward run or its gradient."""
    import diffrax
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import nhjax as nh
    from _timing import run_and_time, timed

    gearbox = nh.examples.gearbox()
    y0 = gearbox.random_initial_state(jax.random.key(0))
    adjoint = diffrax.RecursiveCheckpointAdjoint(checkpoints=checkpoints)

    def loss(y0):
        solution = nh.integrate(
            gearbox.canonical, nh.GonzalezR(), y0, 0.1, steps, save_every=steps, adjoint=adjoint
        )
        q, p = solution.ys
        return jnp.sum(q[-1] ** 2) + jnp.sum(jnp.cos(p[-1]))

    function = jax.jit(loss if mode == "forward" else jax.grad(loss))
    compile_s = timed(lambda y: function.lower(y).compile(), y0)
    compiled_peak = _peak_mib()
    value, seconds = run_and_time(function, y0, repeats=repeats)
    finite = all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(value))
    return dict(
        seconds=seconds,
        compile_s=compile_s,
        peak_after_compile_mib=compiled_peak,
        peak_mib=_peak_mib(),
        finite=finite,
    )


def _in_subprocess(mode: str, steps: int, repeats: int, checkpoints: int | None) -> dict:
    command = [sys.executable, __file__, "--child", mode, "--steps", str(steps), "--repeats", str(repeats)]
    if checkpoints is not None:
        command += ["--checkpoints", str(checkpoints)]
    output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--checkpoints", type=int, default=None)
    parser.add_argument("--child", choices=("forward", "gradient"))
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "gradients.json"))
    options = parser.parse_args()
    if options.child:
        print(json.dumps(measure(options.child, options.steps, options.repeats, options.checkpoints)))
        return

    from _timing import write

    forward = _in_subprocess("forward", options.steps, options.repeats, None)
    print(f"forward, {options.steps} steps: {forward}")
    results = dict(steps=options.steps, dt=0.1, forward=forward, gradients={})
    for checkpoints in (None, 1000):
        gradient = _in_subprocess("gradient", options.steps, options.repeats, checkpoints)
        gradient["time_ratio_to_forward"] = gradient["seconds"] / forward["seconds"]
        label = "default (log n)" if checkpoints is None else f"{checkpoints} checkpoints"
        results["gradients"][label] = gradient
        print(f"gradient, {label}: {gradient}")
    write(results, options.out)


if __name__ == "__main__":
    main()
