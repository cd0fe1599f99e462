"""Ensembles on an accelerator: trajectory-steps per second from one trajectory to
200 000, beside the vmapped implicit-midpoint yardstick (`_timing.yardstick`) at the same
batch, timed in the same process on the default device (a GPU where JAX has one).

Sections of `benchmarks/results/gpu.json` in the order measured (each written as soon as
it is measured, so that a run cut short keeps what it measured):

- `throughput`: for GONZALEZ-R and SI-DLA on the gearbox (canonical) and
  DiscreteGradient on the n = 3 quartic (adapted), h = 0.1: one trajectory of
  `--single-steps` steps (µs/step), then vmapped batches of `--steps` steps (one save),
  trajectory-steps/s, the yardstick's at the same batch and size of run, and the time
  ratio method / yardstick; with the compile time and the failed trajectories.
- `invariants`: one GONZALEZ-R trajectory of `--single-steps` steps on the default
  device: largest relative energy error and constraint residual, and the distance of
  its final state to the same run on the CPU.
- `gradients`: reverse-mode derivatives of a loss on the final state through 2 000
  GONZALEZ-R steps: forward run, reverse run and their compile times.
- `levers` (`--levers`): GONZALEZ-R on the gearbox again, one trajectory and a batch of
  200, in child processes, each with one candidate value of `XLA_FLAGS` (`LEVERS`:
  command buffers, CUDA graphs for loops; a flag XLA does not know ends its child,
  which is recorded), and in each child the runs of `LOOPS`: through `nhjax.integrate`
  (its loop: a `lax.while_loop` of the steps between saves, which stops the run at its
  end or at a failure) or a bare `lax.scan` of the steps
  (`_timing.bare_loop`); the step's rare branches by `lax.cond` or evaluated and
  selected; the chord iteration by its while loop or a loop of a fixed trip count
  first (the default chord iteration with `fixed_trip=FIXED_TRIP`, then its while
  loop). Each while-loop
  iteration and each `lax.cond` copies a predicate to the host: a GONZALEZ-R step on
  the gearbox has the loop's condition and a `lax.cond` in it, the chord matrix's `rarely`,
  and per chord iteration (4.4 a step) the loop's condition and the discrete
  gradient's `rarely`; with both branches selected and a fixed trip count, one
  condition per step is left beside the loop's.
- `cpu`: the same figures for batches 1 and 200 on the host's CPU, where the default
  device is not a CPU.

`--budget-s` bounds the whole run: batches and sections that would start after it are
recorded as skipped.

Run: python benchmarks/gpu.py [--repeats 3] [--quick] [--levers] [--budget-s 480]
(on a machine with a GPU and JAX installed for it; with the checkout on `PYTHONPATH`,
no install of nhjax is needed). `--quick`: batches up to 2 000 and shorter runs, a smoke
test that also runs on a CPU. With minutes of a GPU, `--levers --single-steps 5000
--budget-s 370` measures the throughput table, the invariants, the gradients and the
first levers; a section that has started runs to its end (a lever's child too), so
allow a few minutes beyond the budget.
"""

import contextlib
import dataclasses
import json
import os
import pathlib
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np


jax.config.update("jax_enable_x64", True)

import nhjax as nh  # noqa: E402
from _timing import bare_loop_batch_rate, bare_loop_per_step, batch_rate, machine, options, per_step, run_and_time, yardstick  # noqa: E402
import nhjax._rare_branch as rare_branch  # noqa: E402
from nhjax._solver.base import default_root_finder  # noqa: E402


BATCHES = (1, 200, 2_000, 20_000, 200_000)
QUICK_BATCHES = (1, 200, 2_000)
DT = 0.1
# Candidate XLA flags for the per-step latency of small batches: XLA:GPU's command
# buffers (CUDA graphs) for the operations of a loop body, loops included.
LEVERS = {
    "default": "",
    "command buffers with loops": "--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,WHILE,CONDITIONAL",
    "command buffers, graphs of any size": (
        "--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,WHILE,CONDITIONAL "
        "--xla_gpu_graph_min_graph_size=1"
    ),
    "no command buffers": "--xla_gpu_enable_command_buffer=",
}
# Iterations of the chord loop of fixed trip count: at h = 0.1, 99.6% of the gearbox's
# steps take at most 6 (a while loop takes the rest).
FIXED_TRIP = 6
# (loop, branches, chord loop) of each lever's runs, in the order run: "both branches"
# sets `nhjax._rare_branch.EVALUATE_BOTH_BRANCHES` (the rare branches of a step, such
# as the discrete gradient's for nearly equal points, evaluated and selected instead of
# a `lax.cond` per chord iteration) for the runs from there on.
LOOPS = (
    ("integrate", "cond", "while"),
    ("bare scan", "cond", "while"),
    ("integrate", "both branches", "while"),
    ("bare scan", "both branches", "while"),
    ("integrate", "both branches", "fixed trip"),
    ("bare scan", "both branches", "fixed trip"),
)


def _cases():
    """(name, system, method, states(count)) for each method measured."""
    gearbox = nh.examples.gearbox()
    quartic = nh.examples.chaotic_quartic(3)

    def gearbox_states(count):
        return jax.vmap(gearbox.random_initial_state)(jax.random.split(jax.random.key(1), count))

    def quartic_states(count):
        return quartic.random_initial_states(jax.random.key(2), count)

    return (
        ("GONZALEZ-R (gearbox)", gearbox.canonical, nh.GonzalezR(), gearbox_states),
        ("SI-DLA (gearbox)", gearbox.canonical, nh.SIDLA(), gearbox_states),
        ("DiscreteGradient (quartic, adapted)", quartic.adapted, nh.DiscreteGradient(), quartic_states),
    )


def _first(states):
    return jax.tree.map(lambda leaf: leaf[0], states)


class _Report:
    """The JSON file, rewritten after every section; and the time budget."""

    def __init__(self, path, budget_s):
        self.path, self.budget_s, self.start = pathlib.Path(path), budget_s, time.perf_counter()
        device = jax.devices()[0]
        self.results = dict(
            device=device.device_kind,
            platform=device.platform,
            jaxlib=jaxlib.__version__,
            xla_flags=os.environ.get("XLA_FLAGS", ""),
            dt=DT,
        )

    def left(self) -> bool:
        return time.perf_counter() - self.start < self.budget_s

    def save(self, section, value):
        self.results[section] = value
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text(json.dumps(dict(self.results, machine=machine(), jax=jax.__version__), indent=2))
        print(f"{section}: saved to {self.path}", flush=True)


def _throughput(report, batches, steps, single_steps, repeats, device=None):
    """The `throughput` table on `device` (default: the default device); the yardstick
    timed once for each batch."""
    table, yardsticks = {}, {}
    with jax.default_device(device) if device is not None else contextlib.nullcontext():
        for name, system, method, states in _cases():
            rows = {}
            for batch in batches:
                if not report.left():
                    rows[str(batch)] = "skipped (budget)"
                    continue
                if batch == 1:
                    y0 = _first(states(1))
                    us, compile_s, iterations = per_step(system, method, y0, single_steps, repeats, dt=DT)
                    if 1 not in yardsticks:
                        yardsticks[1] = yardstick(single_steps, repeats)
                    yard_us = yardsticks[1]
                    rows["1"] = dict(
                        steps=single_steps, us_per_step=us, trajectory_steps_per_s=1e6 / us, compile_s=compile_s,
                        iterations_per_step=iterations, yardstick_us_per_step=yard_us, time_over_yardstick=us / yard_us,
                    )
                else:
                    start = time.perf_counter()
                    rate, failed = batch_rate(system, method, states(batch), steps, repeats, dt=DT)
                    if batch not in yardsticks:
                        yardsticks[batch] = yardstick(steps, repeats, batch=batch)
                    yard_rate = yardsticks[batch]
                    rows[str(batch)] = dict(
                        steps=steps, trajectory_steps_per_s=rate, failed=failed, yardstick_trajectory_steps_per_s=yard_rate,
                        time_over_yardstick=yard_rate / rate, wall_s=time.perf_counter() - start,
                    )
                print(name, batch, rows[str(batch)], flush=True)
            table[name] = rows
    return table


def _invariants(single_steps):
    """Energy and constraint errors of one GONZALEZ-R run on the default device, and
    its distance to the same run on the CPU."""
    gearbox = nh.examples.gearbox()
    y0 = gearbox.random_initial_state(jax.random.key(0))
    run = jax.jit(lambda y: nh.integrate(gearbox.canonical, nh.GonzalezR(), y, DT, single_steps, save_every=200))
    solution = run(y0)
    energy = np.asarray(solution.energy)
    residual = jax.vmap(lambda q, p: gearbox.canonical.constraint_residual((q, p), None))(*solution.ys)
    result = dict(
        steps=single_steps,
        relative_energy_error=float(np.max(np.abs(energy - energy[0])) / abs(energy[0])),
        constraint_residual=float(jnp.max(jnp.abs(residual))),
    )
    cpu = jax.devices("cpu")[0]
    if jax.devices()[0].platform != "cpu":
        with jax.default_device(cpu):
            on_cpu = jax.jit(
                lambda y: nh.integrate(gearbox.canonical, nh.GonzalezR(), y, DT, single_steps, save_every=200)
            )(jax.device_put(y0, cpu))
        result["final_state_distance_to_cpu"] = max(
            float(np.max(np.abs(np.asarray(a[-1]) - np.asarray(b[-1]))))
            for a, b in zip(jax.tree.leaves(solution.ys), jax.tree.leaves(on_cpu.ys))
        )
    return result


def _gradients(steps, repeats):
    """Forward and reverse-mode times of a loss on the final state after `steps`
    GONZALEZ-R steps of the gearbox."""
    gearbox = nh.examples.gearbox()
    y0 = gearbox.random_initial_state(jax.random.key(0))

    def loss(y):
        final = nh.integrate(gearbox.canonical, nh.GonzalezR(), y, DT, steps, save_every=steps).ys
        return sum(jnp.sum(leaf[-1] ** 2) for leaf in jax.tree.leaves(final))

    result = {}
    for label, function in (("forward", jax.jit(loss)), ("reverse", jax.jit(jax.grad(loss)))):
        start = time.perf_counter()
        function.lower(y0).compile()
        compile_s = time.perf_counter() - start
        output, seconds = run_and_time(function, y0, repeats=repeats)
        finite = all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(output))
        result[label] = dict(seconds=seconds, compile_s=compile_s, finite=finite)
    result["steps"] = steps
    result["reverse_over_forward"] = result["reverse"]["seconds"] / result["forward"]["seconds"]
    return result


def _lever_child(steps, single_steps, repeats):
    """In a child process: one trajectory and a batch of 200 of GONZALEZ-R on the
    gearbox, by each of `LOOPS`, under this process's `XLA_FLAGS`, as one JSON line."""
    _, system, method, states = _cases()[0]
    chord = default_root_finder(jax.tree.leaves(states(1))[0].dtype)
    fixed = nh.GonzalezR(root_finder=dataclasses.replace(chord, fixed_trip=FIXED_TRIP))
    results = {}
    for loop, branches, chord in LOOPS:
        if branches == "both branches" and not rare_branch.EVALUATE_BOTH_BRANCHES:
            rare_branch.EVALUATE_BOTH_BRANCHES = True
            jax.clear_caches()  # the steps traced so far hold their conditionals
        chosen = fixed if chord == "fixed trip" else method
        label = ", ".join((loop, branches, chord))
        if loop == "integrate":
            us, compile_s, _ = per_step(system, chosen, _first(states(1)), single_steps, repeats, dt=DT)
            rate, failed = batch_rate(system, chosen, states(200), steps, repeats, dt=DT)
            results[label] = dict(us_per_step=us, compile_s=compile_s, batch_200_trajectory_steps_per_s=rate,
                                  failed=failed)
        else:
            us = bare_loop_per_step(system, chosen, _first(states(1)), single_steps, repeats, dt=DT)
            rate = bare_loop_batch_rate(system, chosen, states(200), steps, repeats, dt=DT)
            results[label] = dict(us_per_step=us, batch_200_trajectory_steps_per_s=rate)
        print(label, results[label], file=sys.stderr, flush=True)
    print("LEVER " + json.dumps(results), flush=True)


def _levers(report, steps, single_steps, repeats):
    results = {}
    for label, flags in LEVERS.items():
        if not report.left():
            results[label] = "skipped (budget)"
            continue
        # The parent holds JAX's preallocated share of the device's memory.
        environment = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} {flags}".strip(),
                           XLA_PYTHON_CLIENT_PREALLOCATE="false")
        command = [sys.executable, __file__, "--lever-child", "1", "--steps", str(steps),
                   "--single-steps", str(single_steps), "--repeats", str(repeats)]
        completed = subprocess.run(command, env=environment, capture_output=True, text=True)
        lines = [line for line in completed.stdout.splitlines() if line.startswith("LEVER ")]
        if completed.returncode == 0 and lines:
            results[label] = dict(json.loads(lines[-1][len("LEVER "):]), xla_flags=flags, fixed_trip=FIXED_TRIP)
        else:
            results[label] = dict(xla_flags=flags, failed=f"exit {completed.returncode}: {completed.stderr[-400:]}")
        print(label, results[label], flush=True)
    return results


def main():
    arguments = options(
        __doc__, "gpu", repeats=3, steps=200, single_steps=20_000, gradient_steps=2_000, budget_s=480.0,
        quick=False, levers=False, lever_child=0,
    )
    if arguments.lever_child:
        _lever_child(arguments.steps, arguments.single_steps, arguments.repeats)
        return
    if arguments.quick:
        arguments.single_steps, arguments.gradient_steps = min(arguments.single_steps, 2_000), 200
    batches = QUICK_BATCHES if arguments.quick else BATCHES
    report = _Report(arguments.out, arguments.budget_s)
    report.save("throughput", _throughput(report, batches, arguments.steps, arguments.single_steps, arguments.repeats))
    if report.left():
        report.save("invariants", _invariants(arguments.single_steps))
    if report.left():
        report.save("gradients", _gradients(arguments.gradient_steps, arguments.repeats))
    if arguments.levers and report.left():
        report.save("levers", _levers(report, arguments.steps, min(arguments.single_steps, 2_000), arguments.repeats))
    if jax.devices()[0].platform != "cpu" and report.left():
        report.save("cpu", _throughput(report, (1, 200), arguments.steps, arguments.single_steps, arguments.repeats,
                                       device=jax.devices("cpu")[0]))
    print(f"wrote {report.path} in {time.perf_counter() - report.start:.0f} s")


if __name__ == "__main__":
    main()
