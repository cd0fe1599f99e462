"""Derivatives through long GONZALEZ-R runs: their compile time, their time against the
forward run's, and peak memory. On the gearbox (metric the identity) every mode below;
with `--systems`, also on systems whose metric depends on the configuration, H written
with a linear solve by M(q) as users write it: the Chaplygin sleigh in canonical
coordinates (h = 0.1) and Euler's disk (`nhjax.examples.rolling_disk_3d`, h = 0.01) from
its mass matrix and from its Lagrangian, and a forced system, the differential-drive
robot under two torque pieces with its wheels' friction (h = 0.05; its loss includes the
work and the dissipated energy), in the modes `forward`, `reverse` and `forward-mode`.

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
turn after the memory is recorded. Compile time is tracing and lowering
(`trace_and_lower_s`) plus XLA's compilation, with its default emitters (`compile_s`)
and, of the same lowered program after the memory figures, with its loop emitter
(`loop_emitter_compile_s`; the README says how to choose it); the program's size is
`hlo_lines`, lines of its optimised HLO.

With `--parts`, on those systems also where the reverse-mode derivative's time goes
(`_profile.derivative_parts`: the recording, the replay with and without
derivatives, and a step's residual, Jacobian and linearisation), µs per step, and
where its compilation goes (`_profile.derivative_program_sizes`: the size and XLA's
compile time of each of those programs, and the reversed replay's instructions by
where they come from).

With `--xla-settings`, on each system the reverse-mode derivative (with its time ratio to
the forward run and its compile times) under each of the XLA settings of
`XLA_SETTINGS`, each in its own process, the settings taken in turn `--rounds` times:
XLA's defaults, the `nhjax` command's whole-loop flag, and that flag with XLA:CPU's
YNNPACK fusions turned off (the README's performance paragraphs say why the last one
differs); results to results/gradients_xla_settings.json.

Run: python benchmarks/gradients.py [--steps N ...] [--repeats R] [--systems NAME ...] [--parts]
     python benchmarks/gradients.py --xla-settings --systems disk sleigh --steps 2000 [--rounds R]
Medians over repeats; results go to benchmarks/results/gradients.json, each system's
with the `XLA_FLAGS` it ran under; those under the `nhjax` command's whole-loop flag
(the README's performance paragraphs) to results/gradients_whole_loops.json (`--out`).
"""

import argparse
import json
import os
import pathlib
import resource
import statistics
import subprocess
import sys

from _nhjax_command import WHOLE_LOOPS


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


def _system(name: str):
    """(system, start, step size, args) by name."""
    import jax
    import jax.numpy as jnp
    import nhjax as nh

    if name == "gearbox":
        gearbox = nh.examples.gearbox()
        return gearbox.canonical, gearbox.random_initial_state(jax.random.key(0)), 0.1, None
    if name == "sleigh":
        sleigh = nh.examples.chaplygin_sleigh()
        start = sleigh.from_adapted(jnp.array([0.0, 0.0, 0.1, 0.3, -0.6]), sleigh.args)
        return sleigh.canonical, start, 0.1, sleigh.args
    if name == "robot":
        robot = nh.examples.differential_drive(torques=((0.05, 0.08), (0.1, -0.02)), duration=2.0)
        return robot.canonical, robot.start("canonical"), 0.05, robot.args
    from scaling import DISK_START

    disk = nh.examples.rolling_disk_3d()
    start = disk.state(**DISK_START)
    form = dict(disk=disk.canonical, **{"disk-lagrangian": disk.canonical_from_lagrangian})[name]
    return form, start, 0.01, disk.args


_SYSTEMS = ("gearbox", "sleigh", "disk", "disk-lagrangian", "robot")
# `--xla-settings`: XLA_FLAGS by name. XLA:CPU compiles a loop into one function only
# where no operation of its body goes to a library: the whole-loop flag raises the size
# limit, and the empty YNNPACK fusion type keeps matrix products out of YNNPACK.
XLA_SETTINGS = {
    "defaults": "",
    "whole loops": WHOLE_LOOPS,
    "whole loops, no YNNPACK fusions": f"{WHOLE_LOOPS} --xla_cpu_experimental_ynn_fusion_type=",
}
# The modes on the systems beside the gearbox: nhjax's default routes.
_DEFAULT_MODES = ("forward", "reverse", "forward-mode")


def final_state_loss(states):
    """The differentiated scalar: a smooth function of the last saved (q, p)."""
    import jax.numpy as jnp

    q, p = states
    return jnp.sum(q[-1] ** 2) + jnp.sum(jnp.cos(p[-1]))


def parts(system_name: str, steps: int, repeats: int) -> dict:
    """In this process: where the reverse-mode derivative's time goes
    (`us_per_step`, `_profile.derivative_parts`), and its compilation
    (`program_sizes`, `_profile.derivative_program_sizes`)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import nhjax as nh
    from _profile import derivative_parts, derivative_program_sizes

    system, y0, dt, args = _system(system_name)
    return dict(
        us_per_step=derivative_parts(system, nh.GonzalezR(), y0, dt, steps, repeats, final_state_loss, args=args),
        program_sizes=derivative_program_sizes(system, nh.GonzalezR(), y0, dt, steps, final_state_loss, args=args),
    )


def measure(system_name: str, mode: str, steps: int, repeats: int) -> dict:
    """In this process: compile and time the forward run or its gradient."""
    import diffrax
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import nhjax as nh
    from _timing import CompileTimes, run_and_time, run_and_time_interleaved

    system, y0, dt, args = _system(system_name)
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
        solution = nh.integrate(system, nh.GonzalezR(), y0, dt, steps, args=args, save_every=steps, adjoint=adjoint)
        loss = final_state_loss(solution.ys)
        if system.is_forced():  # the energy ledger's derivatives too
            loss = loss + solution.work[-1] - solution.dissipated[-1]
        return loss

    function = jax.jit(transform(loss))
    compile_times = CompileTimes(function, y0)
    compiled_peak = _peak_mib()
    value, seconds = run_and_time(function, y0, repeats=repeats)
    finite = all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(value))
    result = dict(
        seconds=seconds,
        peak_after_compile_mib=compiled_peak,
        peak_mib=_peak_mib(),
        finite=finite,
    )
    if mode != "forward":
        # The time ratio from this process, the forward run timed in turn with the
        # derivative, so that the machine's drift falls on both alike.
        _, times = run_and_time_interleaved(dict(derivative=function, forward=jax.jit(loss)), y0, repeats=repeats)
        result["time_ratio_to_forward"] = times["derivative"] / times["forward"]
    # After the memory figures: the same program compiled with XLA:CPU's loop emitter.
    result.update(compile_times.times())
    return result


def _in_subprocess(system: str, mode: str, steps: int, repeats: int, xla_flags: str | None = None) -> dict:
    """A measurement in a process of its own, under `xla_flags` where given (else this
    process's `XLA_FLAGS`)."""
    command = [
        sys.executable, __file__, "--child", mode, "--systems", system, "--steps", str(steps), "--repeats", str(repeats)
    ]
    environment = os.environ if xla_flags is None else {**os.environ, "XLA_FLAGS": xla_flags}
    output = subprocess.run(command, check=True, capture_output=True, text=True, env=environment).stdout
    return json.loads(output.strip().splitlines()[-1])


def compare_xla_settings(systems, steps: int, repeats: int, rounds: int) -> dict:
    """Per system, the reverse-mode derivative under each of `XLA_SETTINGS`, the
    settings in turn `rounds` times so that the machine's drift falls on all alike:
    every run, and the medians of its time, its ratio to the forward run and its
    compile times."""
    compared = {}
    for system in systems:
        runs = {name: [] for name in XLA_SETTINGS}
        for _ in range(rounds):
            for name, flags in XLA_SETTINGS.items():
                runs[name].append(_in_subprocess(system, "reverse", steps, repeats, xla_flags=flags))
                print(f"{system}, {steps} steps, reverse, {name}: {runs[name][-1]}", flush=True)
        compared[system] = {
            name: dict(
                xla_flags=XLA_SETTINGS[name],
                runs=measured,
                **{
                    f"median_{key}": statistics.median(run[key] for run in measured)
                    for key in ("seconds", "time_ratio_to_forward", "trace_and_lower_s", "compile_s")
                },
            )
            for name, measured in runs.items()
        }
    return dict(steps=steps, repeats=repeats, rounds=rounds, systems=compared)


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, nargs="+", default=[2_000, 100_000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--systems", nargs="+", choices=_SYSTEMS, default=["gearbox"])
    parser.add_argument("--child", choices=_MODES + ("parts",))
    parser.add_argument("--parts", action="store_true", help="also where the derivative's time goes, per system")
    parser.add_argument("--xla-settings", action="store_true", help="reverse mode under each of XLA_SETTINGS")
    parser.add_argument("--rounds", type=int, default=2, help="with --xla-settings: turns through the settings")
    parser.add_argument("--out", help="default: results/gradients.json (results/gradients_xla_settings.json)")
    options = parser.parse_args()
    results_directory = pathlib.Path(__file__).parent / "results"
    if options.xla_settings:
        from _timing import write

        compared = compare_xla_settings(options.systems, options.steps[0], options.repeats, options.rounds)
        write(compared, options.out or str(results_directory / "gradients_xla_settings.json"))
        return
    options.out = options.out or str(results_directory / "gradients.json")
    if options.child == "parts":
        print(json.dumps(parts(options.systems[0], options.steps[0], options.repeats)))
        return
    if options.child:
        print(json.dumps(measure(options.systems[0], options.child, options.steps[0], options.repeats)))
        return

    import jax
    from _timing import machine, write

    path = pathlib.Path(options.out)
    results = json.loads(path.read_text()) if path.exists() else {}
    results.setdefault("runs", {})
    results.setdefault("systems", {})
    for system in options.systems:
        modes = _MODES if system == "gearbox" else _DEFAULT_MODES
        for steps in options.steps:
            run = {}
            for mode in modes:
                run[mode] = _in_subprocess(system, mode, steps, options.repeats)
                print(f"{system}, {steps} steps, {mode}: {run[mode]}", flush=True)
            if system == "gearbox":
                results["dt"] = 0.1
                results["runs"][str(steps)] = run
            else:
                if options.parts:
                    measured = _in_subprocess(system, "parts", steps, options.repeats)
                    run["parts_us_per_step"], run["parts_program_sizes"] = measured["us_per_step"], measured["program_sizes"]
                    print(f"{system}, {steps} steps, parts: {measured}", flush=True)
                entry = results["systems"].setdefault(system, {})
                entry[str(steps)] = run
                entry["jax"], entry["machine"] = jax.__version__, machine()
    write(results, options.out)


if __name__ == "__main__":
    main()
