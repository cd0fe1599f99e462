"""Keeping the chord matrix from step to step (`reuse_chord_matrix=True`) against forming
it at every step, for GONZALEZ-R, GONZALEZ-F and the energy-preserving collocation,
timed in turns in one process (`_timing.run_and_time_interleaved`).

Cases: the paper's gearbox, n = 3 quartic and sleigh (GONZALEZ-R, h = 0.1), Euler's disk
with H from its mass matrix and from its Lagrangian (h = 0.01), the disk's mass-matrix form
as a batch of 32 trajectories under `jax.vmap` (momenta scaled by 1 to 1.01: under
`vmap` a step forms the whole batch's matrices when any trajectory needs a fresh one,
`nhjax._rare_branch.rarely`), the synthetic systems of
`scaling.py` at n = 16, 32 and 64 and a tractor pulling 5 trailers (h = 0.05: n = 8,
k = 6, a metric that depends on q); the collocation of order 4, 6 and 8 on the
quartic and of order 6 and 8 on the gearbox, at the step sizes where
`composition.py` finds them cheapest; GONZALEZ-F on the gearbox, the n = 3 quartic, the
contact oscillator (M = I), the sleigh and the 2D rolling disk (h = 0.1), Euler's disk
(h = 0.01) and tractors pulling 5, 13 and 29 trailers (n = 8, 16 and 32, h = 0.05).
For each: µs/step (median) both ways and their
ratio, iterations per step both ways, chord matrices formed per step when kept, and the
largest difference of the final states and of the energy errors. GONZALEZ-R's chord
matrix is the one with the frame held either way (`exact_chord_matrix=False`), so that
the figures measure keeping it alone.

Which matrix, and whether to keep it (`matrix_choices`): on the systems whose metric
depends on q (Euler's disk in both forms, 2 000 steps; the 5 trailers, 625; the
sleigh, 2 000), GONZALEZ-R with the frame held or the exact matrix
(`exact_chord_matrix`), each formed at every step or kept, in turns: µs/step, the
ratio to the held matrix formed at every step, iterations per step, and compile
seconds (`_timing.CompileTimes`) and lines of HLO, since the exact matrix and the kept
one's conditional make a larger program. The default there is the exact matrix, kept.

Results: benchmarks/results/chord_reuse.json.
Run: python benchmarks/chord_reuse.py [--repeats 7] [--choices-only] [--only TEXT]
(`--choices-only`: the matrix choices alone, the other cases keeping their last results;
`--only TEXT`: the cases whose name contains TEXT alone, the others and the matrix
choices keeping theirs)
"""

import json
import pathlib

import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

import nhjax as nh  # noqa: E402
import scaling  # noqa: E402
from _timing import CompileTimes, options, run_and_time_interleaved, write  # noqa: E402


_BATCH = 32


def _gonzalez_r(keep):
    """GONZALEZ-R with its chord matrix kept or formed at every step, the frame held
    either way."""
    return nh.GonzalezR(reuse_chord_matrix=keep, exact_chord_matrix=False)


def _gonzalez_f(keep):
    return nh.GonzalezF(reuse_chord_matrix=keep)


def _cases():
    gearbox, quartic = nh.examples.gearbox(), nh.examples.chaotic_quartic(3)
    sleigh, disk = nh.examples.chaplygin_sleigh(), nh.examples.rolling_disk_3d()
    paper = {
        "gearbox": (gearbox.canonical, gearbox.random_initial_state(jax.random.key(0)), None),
        "quartic n = 3": (quartic.canonical, quartic.from_adapted(quartic.initial_state(0.7)), None),
        "sleigh": (sleigh.canonical, sleigh.start("canonical"), sleigh.args),
    }
    cases = {}
    for name, problem in paper.items():
        cases[f"GONZALEZ-R, {name}"] = (*problem, _gonzalez_r, 0.1, 1000)
    for name, system in (("mass-matrix H", disk.canonical), ("Lagrangian", disk.canonical_from_lagrangian)):
        cases[f"GONZALEZ-R, Euler's disk ({name})"] = (
            system, disk.initial_state(), disk.args, _gonzalez_r, 0.01, 500
        )
    q0, p0 = disk.initial_state()
    batch = (jnp.broadcast_to(q0, (_BATCH, *q0.shape)), p0 * (1 + 0.01 * jnp.arange(_BATCH) / _BATCH)[:, None])
    cases[f"GONZALEZ-R, Euler's disk (mass-matrix H), batch of {_BATCH}"] = (
        disk.canonical, batch, disk.args, _gonzalez_r, 0.01, 200
    )
    trailers = nh.examples.tractor_trailers(5)
    cases["GONZALEZ-R, tractor pulling 5 trailers"] = (
        trailers.canonical, trailers.initial_state(), trailers.args, _gonzalez_r,
        scaling.H, 200,
    )
    for n, steps in ((16, 100), (32, 50), (64, 20)):
        cases[f"GONZALEZ-R, synthetic n = {n}"] = (
            scaling.SYSTEM, scaling.initial_state(n), None, _gonzalez_r,
            scaling.H, steps,
        )
    oscillator, disk_2d = nh.examples.contact_oscillator(), nh.examples.rolling_disk()
    for name, problem in {
        **paper,
        "contact oscillator": (oscillator.canonical, oscillator.start("canonical"), oscillator.args),
        "2D rolling disk": (disk_2d.canonical, disk_2d.start("canonical"), disk_2d.args),
    }.items():
        cases[f"GONZALEZ-F, {name}"] = (*problem, _gonzalez_f, 0.1, 1000)
    cases["GONZALEZ-F, Euler's disk (mass-matrix H)"] = (
        disk.canonical, disk.initial_state(), disk.args, _gonzalez_f, 0.01, 500
    )
    for count, steps in ((5, 200), (13, 100), (29, 40)):
        train = nh.examples.tractor_trailers(count)
        cases[f"GONZALEZ-F, tractor pulling {count} trailers"] = (
            train.canonical, train.initial_state(), train.args, _gonzalez_f, scaling.H, steps
        )
    for name, orders in (("quartic n = 3", ((4, 200), (6, 100), (8, 40))), ("gearbox", ((6, 50), (8, 32)))):
        for order, steps in orders:
            cases[f"collocation {order}, {name}"] = (
                *paper[name],
                lambda keep, order=order: nh.EnergyPreservingCollocation(order, reuse_chord_matrix=keep),
                10.0 / steps,
                steps,
            )
    return cases


def _measure(system, y0, args, method_of, h, steps, repeats):
    """Both ways in turns; a batched `y0` (leading axis beyond the state's) runs under
    `jax.vmap`, its counts the batch's means."""
    batched = jnp.ndim(y0[0]) == 2

    def run_of(method):
        run = lambda y: nh.integrate(system, method, y, h, steps, args=args, save_every=steps)  # noqa: E731
        return jax.jit(jax.vmap(run) if batched else run)

    runs = {label: run_of(method_of(keep)) for label, keep in (("fresh", False), ("kept", True))}
    solutions, seconds = run_and_time_interleaved(runs, y0, repeats=repeats)
    fresh, kept = solutions["fresh"], solutions["kept"]
    difference = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(fresh.ys), jax.tree.leaves(kept.ys)))

    def energy_error(solution):
        energy = solution.energy
        return float(jnp.max(jnp.abs(energy - energy[..., :1]) / jnp.abs(energy[..., :1])))

    def per_step(count):
        return float(jnp.mean(count)) / steps

    return dict(
        h=h,
        steps=steps,
        fresh_us_per_step=seconds["fresh"] / steps * 1e6,
        kept_us_per_step=seconds["kept"] / steps * 1e6,
        kept_over_fresh=seconds["kept"] / seconds["fresh"],
        fresh_iterations_per_step=per_step(fresh.stats["root_find_steps"]),
        kept_iterations_per_step=per_step(kept.stats["root_find_steps"]),
        kept_matrices_per_step=per_step(kept.stats["chord_matrices"]),
        final_state_difference=difference,
        energy_errors=dict(fresh=energy_error(fresh), kept=energy_error(kept)),
    )


# (frame held or exact matrix, kept or formed at every step) for `matrix_choices`.
_CHOICES = {
    "held, fresh": dict(exact_chord_matrix=False, reuse_chord_matrix=False),
    "exact, fresh": dict(exact_chord_matrix=True, reuse_chord_matrix=False),
    "held, kept": dict(exact_chord_matrix=False, reuse_chord_matrix=True),
    "exact, kept": dict(exact_chord_matrix=True, reuse_chord_matrix=True),
}


def _matrix_choices(repeats):
    """`_CHOICES` on the systems whose metric depends on q, timed in turns (see the
    module docstring): {problem: {choice: figures}}, and each problem's h and steps."""
    disk, sleigh = nh.examples.rolling_disk_3d(), nh.examples.chaplygin_sleigh()
    trailers = nh.examples.tractor_trailers(5)
    problems = {
        "Euler's disk (mass-matrix H)": (disk.canonical, disk.state(**scaling.DISK_START), disk.args, 0.01, 2000),
        "Euler's disk (Lagrangian)": (
            disk.canonical_from_lagrangian, disk.state(**scaling.DISK_START), disk.args, 0.01, 2000
        ),
        "tractor pulling 5 trailers": (trailers.canonical, trailers.initial_state(), trailers.args, scaling.H, 625),
        "sleigh": (sleigh.canonical, sleigh.start("canonical"), sleigh.args, 0.1, 2000),
    }
    table = {}
    for name, (system, y0, args, h, steps) in problems.items():
        runs, programs = {}, {}
        for label, choice in _CHOICES.items():
            method = nh.GonzalezR(**choice)
            runs[label] = jax.jit(
                lambda y, method=method: nh.integrate(system, method, y, h, steps, args=args, save_every=steps)
            )
            programs[label] = CompileTimes(runs[label], y0)
        solutions, seconds = run_and_time_interleaved(runs, y0, repeats=repeats)
        table[name] = {
            label: dict(
                us_per_step=seconds[label] / steps * 1e6,
                over_held_fresh=seconds[label] / seconds["held, fresh"],
                iterations_per_step=float(solutions[label].stats["root_find_steps"]) / steps,
                compile_s=programs[label].compile_s,
                hlo_lines=programs[label].hlo_lines,
            )
            for label in _CHOICES
        }
        print(
            f"{name:30s} "
            + "; ".join(
                f"{label} {row['us_per_step']:.1f} µs ({row['over_held_fresh']:.2f}, {row['compile_s']:.1f} s)"
                for label, row in table[name].items()
            ),
            flush=True,
        )
    return dict(table, h_and_steps={name: problem[3:] for name, problem in problems.items()})


def main():
    arguments = options(__doc__, "chord_reuse", repeats=7, choices_only=False, only="")
    path = pathlib.Path(arguments.out)
    if arguments.choices_only or arguments.only:
        results = json.loads(path.read_text()) if path.exists() else {}
        results.setdefault("cases", {})
    else:
        results = dict(cases={}, repeats=arguments.repeats)
    if not arguments.choices_only:
        for name, (system, y0, args, method_of, h, steps) in _cases().items():
            if arguments.only not in name:
                continue
            row = results["cases"][name] = _measure(system, y0, args, method_of, h, steps, arguments.repeats)
            print(
                f"{name:42s} fresh {row['fresh_us_per_step']:8.1f} µs/step  kept {row['kept_us_per_step']:8.1f}"
                f"  ratio {row['kept_over_fresh']:.2f}  iterations {row['fresh_iterations_per_step']:.2f} ->"
                f" {row['kept_iterations_per_step']:.2f}  matrices/step {row['kept_matrices_per_step']:.2f}",
                flush=True,
            )
    if not arguments.only:
        results["matrix_choices"] = _matrix_choices(arguments.repeats)
    write(results, arguments.out)


if __name__ == "__main__":
    main()
