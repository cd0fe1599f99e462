"""The benchmark suite: nhjax beside what a user would pick instead, all measured in one
run, on the gearbox and the n = 3 chaotic quartic at h = 0.1.

1. Every nhjax method: µs/step for one trajectory, root-finder iterations/step,
   compile time, and trajectory-steps/s for vmapped batches of 1, 10, 200 and 2000.
2. The same simulation to t = 1000 by
   - nhjax's methods (fixed step h = 0.1),
   - GONZALEZ-R in NumPy with one `scipy.optimize.fsolve` per step (`peers.py`),
   - `scipy.integrate.solve_ivp` (DOP853, Radau) on the index-1 ODE written in NumPy,
   - diffrax's Tsit5, Dopri8 and Kvaerno5 on the index-1 ODE (`nhjax.integrate_adaptive`),
   the last two at rtol = atol = 1e-8: seconds per unit of simulated time, energy drift
   and constraint drift at t = 1000, and the ratios to nhjax's GONZALEZ-R.
3. Equal wall time: each non-geometric solver over a range of tolerances, its energy
   error at t = 1000 interpolated (log-log) at the wall time of GONZALEZ-R's run.
4. Scaling: µs/step of GONZALEZ-R (canonical) and of the discrete gradient on the
   analytic reduced form, for the quartic with n = 1, 3, 10, 30, the fitted exponent of
   cost against n, and the time of each part of a step (`_profile.py`).
5. Ensembles split over 2 CPU devices (`sharding.py`, in its own process).
6. Work against precision with the compositions of order 4, 6 and 8 (`composition.py`):
   GONZALEZ-R and GONZALEZ on the reduced form, composed, beside their second-order
   selves, Tsit5 and Dopri8, to t = 10 down to errors of 1e-10; at each target error the
   cheapest run, the cheapest energy-exact run and the cheapest Dopri8 run.

Every time is the median of `--repeats` runs (after a warm-up run). Results go to
benchmarks/results/suite.json and, as tables, benchmarks/results/suite.md.

Run: python benchmarks/suite.py [--repeats 3] [--quick]
(`--quick`: shorter runs, t = 100 instead of 1000, for a smoke test.)
"""

import argparse
import json
import pathlib
import statistics
import subprocess
import sys
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)

import nhjax as nh  # noqa: E402
import composition  # noqa: E402
import peers  # noqa: E402
from _profile import step_parts  # noqa: E402
from _timing import batch_rate, per_step, run_and_time, write  # noqa: E402


H = 0.1
BATCHES = (1, 10, 200, 2000)
NHJAX_METHODS = {
    "GONZALEZ-R": nh.GonzalezR(),
    "GONZALEZ-F": nh.GonzalezF(),
    "SI-DLA": nh.SIDLA(),
    "I-DLA": nh.IDLA(),
    "SPARK": nh.SPARK(),
}
DIFFRAX_SOLVERS = {"Tsit5": diffrax.Tsit5(), "Dopri8": diffrax.Dopri8(), "Kvaerno5": diffrax.Kvaerno5()}
SCIPY_SOLVERS = ("DOP853", "Radau")
STANDARD_TOLERANCE = 1e-8
# Tolerances that bracket GONZALEZ-R's wall time where a solver can reach it; the
# implicit solvers are slower than it at every tolerance, so their loosest ones count.
SWEEP = {"Tsit5": (1e-6, 1e-8, 1e-10, 1e-12, 1e-14), "Dopri8": (1e-6, 1e-8, 1e-10, 1e-12, 1e-14),
         "Kvaerno5": (1e-5, 1e-7), "DOP853": (1e-4, 1e-6, 1e-8), "Radau": (1e-4, 1e-6)}
SCALING_SIZES = (1, 3, 10, 30)


def _problems(batch):
    gearbox = nh.examples.gearbox()
    quartic = nh.examples.chaotic_quartic(3)
    gearbox_states = jax.vmap(gearbox.random_initial_state)(jax.random.split(jax.random.key(1), batch))
    quartic_states = jax.vmap(quartic.from_adapted)(quartic.random_initial_states(jax.random.key(1), batch))
    return {
        "gearbox": dict(
            system=gearbox.canonical, y0=gearbox.random_initial_state(jax.random.key(0)),
            states=gearbox_states, numpy=peers.GEARBOX, adapted=None,
        ),
        "quartic_n3": dict(
            system=quartic.canonical, y0=quartic.from_adapted(quartic.initial_state(0.7)),
            states=quartic_states, numpy=peers.QUARTIC3,
            adapted=(quartic.adapted, quartic.initial_state(0.7), quartic.random_initial_states(jax.random.key(1), batch)),
        ),
    }


def _drift(solution):
    energy = np.abs(np.asarray(solution.energy) / float(solution.energy[0]) - 1)
    constraint = np.max(np.abs(np.asarray(solution.constraint)), axis=-1)
    return dict(
        final_energy_error=float(energy[-1]), max_energy_error=float(energy.max()),
        final_constraint_error=float(constraint[-1]), max_constraint_error=float(constraint.max()),
    )


def methods_table(problem, options):
    """Section 1 for one system."""
    rows = {}
    methods = [(name, problem["system"], method, problem["y0"], problem["states"]) for name, method in NHJAX_METHODS.items()]
    if problem["adapted"] is not None:
        system, x0, states = problem["adapted"]
        methods.append(("DiscreteGradient (reduced form)", system, nh.DiscreteGradient(), x0, states))
    for name, system, method, y0, states in methods:
        us, compile_s, iterations = per_step(system, method, y0, options.steps, options.repeats)
        rates, failed = {}, {}
        for size in BATCHES:
            batch_steps = max(20, min(options.steps, options.batch_work // size))
            subset = jax.tree.map(lambda leaf: leaf[:size], states)
            rates[str(size)], failed[str(size)] = batch_rate(system, method, subset, batch_steps, options.repeats)
        rows[name] = dict(us_per_step=us, compile_s=compile_s, root_find_iterations_per_step=iterations,
                          trajectory_steps_per_s=rates, failed_trajectories=failed)
        print(f"  {name:32s} {us:9.2f} µs/step  compile {compile_s:5.1f} s  batches "
              + "  ".join(f"{size}: {rate:.2e}" for size, rate in rates.items()), flush=True)
    return rows


def long_runs(problem, options):
    """Section 2 for one system: every route to t = options.t1."""
    t1, steps = options.t1, int(round(options.t1 / H))
    system, y0 = problem["system"], problem["y0"]
    q0, p0 = (np.asarray(leaf) for leaf in y0)
    rows = {}
    for name, method in NHJAX_METHODS.items():
        run = jax.jit(lambda y, method=method: nh.integrate(system, method, y, H, steps, save_every=steps // 1000 or 1))
        solution, seconds = run_and_time(run, y0, repeats=options.repeats)
        rows[name] = dict(seconds=seconds, seconds_per_unit_time=seconds / t1, **_drift(solution))

    short = options.numpy_steps
    numpy_step_s = statistics.median(
        [peers.gonzalez_r_numpy(problem["numpy"], q0, p0, H, short)["seconds"] / short for _ in range(options.repeats)]
    )
    numpy_run = peers.gonzalez_r_drift(problem["numpy"], q0, p0, H, steps)
    rows["GONZALEZ-R (NumPy + fsolve)"] = dict(
        seconds=numpy_run["seconds"], seconds_per_unit_time=numpy_step_s / H,
        max_energy_error=numpy_run["max_energy_error"], max_constraint_error=numpy_run["max_constraint_error"],
        us_per_step=numpy_step_s * 1e6,
    )
    for method in SCIPY_SOLVERS:
        runs = [peers.solve_ivp_run(problem["numpy"], q0, p0, t1, method, STANDARD_TOLERANCE, STANDARD_TOLERANCE)
                for _ in range(options.repeats)]
        seconds = statistics.median(run["seconds"] for run in runs)
        rows[f"solve_ivp {method} (index-1, NumPy)"] = dict(
            runs[0], seconds=seconds, seconds_per_unit_time=seconds / t1, rtol=STANDARD_TOLERANCE
        )
    for name, solver in DIFFRAX_SOLVERS.items():
        solution, seconds = _adaptive(system, y0, t1, solver, STANDARD_TOLERANCE, options.repeats)
        rows[f"diffrax {name} (index-1)"] = dict(
            seconds=seconds, seconds_per_unit_time=seconds / t1, rtol=STANDARD_TOLERANCE,
            num_steps=int(solution.stats["num_steps"]), **_drift(solution),
        )
    reference = rows["GONZALEZ-R"]
    rows["GONZALEZ-R (NumPy + fsolve)"]["nhjax_speedup_per_step"] = (
        numpy_step_s / (reference["seconds"] / steps)
    )
    for row in rows.values():
        row["time_ratio_to_gonzalez_r"] = row["seconds_per_unit_time"] / reference["seconds_per_unit_time"]
    for name, row in rows.items():
        print(f"  {name:36s} {row['seconds_per_unit_time'] * 1e3:9.3f} ms per unit time  "
              f"energy {row['max_energy_error']:.1e}  constraint {row['max_constraint_error']:.1e}", flush=True)
    return rows


def _adaptive(system, y0, t1, solver, tolerance, repeats):
    save_at = jnp.linspace(0.0, t1, 1001)

    @jax.jit
    def run(y0):
        return nh.integrate_adaptive(system, y0, t1, method=solver, rtol=tolerance, atol=tolerance,
                                     save_at=save_at, max_steps=10_000_000)

    return run_and_time(run, y0, repeats=repeats)


def equal_wall_time(problem, gonzalez_r_seconds, options):
    """Section 3 for one system: work-precision points of each non-geometric solver, and
    its energy error interpolated at GONZALEZ-R's wall time."""
    system, y0 = problem["system"], problem["y0"]
    q0, p0 = (np.asarray(leaf) for leaf in y0)
    out = {}
    for name, tolerances in SWEEP.items():
        points = []
        for tolerance in tolerances:
            if name in DIFFRAX_SOLVERS:
                solution, seconds = _adaptive(system, y0, options.t1, DIFFRAX_SOLVERS[name], tolerance, options.repeats)
                drift = _drift(solution)
            else:
                runs = [peers.solve_ivp_run(problem["numpy"], q0, p0, options.t1, name, tolerance, tolerance)
                        for _ in range(options.repeats)]
                seconds, drift = statistics.median(run["seconds"] for run in runs), runs[0]
            points.append(dict(rtol=tolerance, seconds=seconds, max_energy_error=drift["max_energy_error"],
                               max_constraint_error=drift["max_constraint_error"]))
        energy, where = _interpolate(points, gonzalez_r_seconds, "max_energy_error")
        constraint, _ = _interpolate(points, gonzalez_r_seconds, "max_constraint_error")
        out[name] = dict(points=points, energy_error_at_equal_time=energy,
                         constraint_error_at_equal_time=constraint, range=where)
    return out


def _interpolate(points, seconds, error_key):
    """(error, range): log(error) against log(time), piecewise linear, at `seconds`. Outside the
    measured range the nearest point is used, and `range` says which way that leans: a
    peer slower than GONZALEZ-R even at its loosest tolerance is credited with that
    tolerance's error although it took longer (favours the peer); a peer faster even at
    its tightest tolerance is charged that tolerance's error although it had time left
    (favours nhjax)."""
    ordered = sorted(points, key=lambda point: point["seconds"])
    times = np.log([point["seconds"] for point in ordered])
    errors = np.log([max(point[error_key], 1e-300) for point in ordered])
    where = "interpolated"
    if np.log(seconds) < times[0]:
        where = "peer slower even at its loosest tolerance (favours the peer)"
    elif np.log(seconds) > times[-1]:
        where = "peer faster even at its tightest tolerance (favours nhjax)"
    return float(np.exp(np.interp(np.log(seconds), times, errors))), where


def scaling(options):
    """Section 4."""
    rows = {}
    for n in options.scaling_sizes:
        quartic = nh.examples.chaotic_quartic(n)
        key_q, key_p = jax.random.split(jax.random.key(n))
        q = 0.5 * jax.random.normal(key_q, (2 * n + 1,))
        p = quartic.canonical.project_momentum(q, 0.5 * jax.random.normal(key_p, (2 * n + 1,)))
        row = {}
        for name, system, method, y0 in (
            ("GONZALEZ-R", quartic.canonical, nh.GonzalezR(), (q, p)),
            ("DiscreteGradient (reduced form)", quartic.adapted, nh.DiscreteGradient(), quartic.to_adapted(q, p)),
        ):
            steps = max(10, options.steps // (1 if n <= 3 else n * n if name == "GONZALEZ-R" else n))
            us, compile_s, iterations = per_step(system, method, y0, steps, options.repeats)
            parts = step_parts(system, method, y0, H, iterations, repeats=max(3, min(200, int(2e5 / us))))
            row[name] = dict(us_per_step=us, compile_s=compile_s, root_find_iterations_per_step=iterations,
                             steps_timed=steps, parts_us=parts)
            print(f"  n = {n:2d} {name:32s} {us:11.1f} µs/step  parts "
                  + "  ".join(f"{key} {value:.1f}" for key, value in parts.items()), flush=True)
        rows[str(n)] = row
    exponents = {}
    for name in ("GONZALEZ-R", "DiscreteGradient (reduced form)"):
        sizes = np.array(options.scaling_sizes, float)
        costs = np.array([rows[str(n)][name]["us_per_step"] for n in options.scaling_sizes])
        exponents[name] = dict(
            all_sizes=float(np.polyfit(np.log(sizes), np.log(costs), 1)[0]),
            largest_two=float(np.log(costs[-1] / costs[-2]) / np.log(sizes[-1] / sizes[-2])),
        )
    return dict(sizes=rows, fitted_exponent=exponents)


def sharding(options):
    """Section 5, in a process of its own (the device count is fixed when JAX starts)."""
    command = [sys.executable, str(pathlib.Path(__file__).parent / "sharding.py"),
               "--repeats", str(options.repeats), "--steps", str(options.sharding_steps)]
    output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def markdown(results):
    lines = [f"# nhjax benchmark suite (h = {H}, medians of {results['repeats']} runs)", ""]
    for system in ("gearbox", "quartic_n3"):
        lines += [f"## {system}: nhjax methods", "",
                  "| method | µs/step | iterations/step | compile s | " + " | ".join(f"batch {b} (traj-steps/s)" for b in BATCHES) + " |",
                  "|---|---:|---:|---:|" + "---:|" * len(BATCHES)]
        for name, row in results["methods"][system].items():
            iterations = row["root_find_iterations_per_step"]
            lines.append(f"| {name} | {row['us_per_step']:.1f} | {'' if iterations is None else f'{iterations:.2f}'} | "
                         f"{row['compile_s']:.1f} | " + " | ".join(f"{row['trajectory_steps_per_s'][str(b)]:.3g}" for b in BATCHES) + " |")
        lines += ["", f"## {system}: to t = {results['t1']:g}", "",
                  "| route | ms per unit time | time / GONZALEZ-R | max energy error | max constraint error |",
                  "|---|---:|---:|---:|---:|"]
        for name, row in results["long_runs"][system].items():
            lines.append(f"| {name} | {row['seconds_per_unit_time'] * 1e3:.3g} | {row['time_ratio_to_gonzalez_r']:.3g} | "
                         f"{row['max_energy_error']:.2e} | {row['max_constraint_error']:.2e} |")
        failures = [f"{name} ({', '.join(f'{count} of {size}' for size, count in row['failed_trajectories'].items() if count)})"
                    for name, row in results["methods"][system].items() if any(row["failed_trajectories"].values())]
        if failures:
            lines += ["", "Trajectories whose root find failed in the batch runs: " + "; ".join(failures) + "."]
        numpy_row = results["long_runs"][system]["GONZALEZ-R (NumPy + fsolve)"]
        lines += ["", f"GONZALEZ-R per step: nhjax {numpy_row['nhjax_speedup_per_step']:.0f}x faster than NumPy + fsolve "
                  f"({numpy_row['us_per_step']:.0f} µs/step).", "",
                  f"## {system}: energy error at GONZALEZ-R's wall time", "",
                  "| solver | energy error at equal time | GONZALEZ-R's error | ratio | constraint error at equal time "
                  "| GONZALEZ-R's | ratio | note |", "|---|---:|---:|---:|---:|---:|---:|---|"]
        ours = results["long_runs"][system]["GONZALEZ-R"]
        for name, row in results["equal_wall_time"][system].items():
            energy, constraint = row["energy_error_at_equal_time"], row.get("constraint_error_at_equal_time", np.nan)
            lines.append(f"| {name} | {energy:.2e} | {ours['max_energy_error']:.2e} | {energy / ours['max_energy_error']:.2g} | "
                         f"{constraint:.2e} | {ours['max_constraint_error']:.2e} | "
                         f"{constraint / ours['max_constraint_error']:.2g} | {row['range']} |")
        lines.append("")
    lines += ["## Scaling with the quartic's n (µs/step)", "", "| n | GONZALEZ-R | reduced DiscreteGradient |", "|---:|---:|---:|"]
    for n, row in results["scaling"]["sizes"].items():
        lines.append(f"| {n} | {row['GONZALEZ-R']['us_per_step']:.4g} | {row['DiscreteGradient (reduced form)']['us_per_step']:.4g} |")
    lines += ["", "Fitted exponents (cost ~ n^e): " + ", ".join(
        f"{name} {e['all_sizes']:.2f} (all sizes), {e['largest_two']:.2f} (largest two)"
        for name, e in results["scaling"]["fitted_exponent"].items()), "",
        "Parts of one GONZALEZ-R step (µs): " + "; ".join(
            f"n = {n}: " + ", ".join(f"{k} {v:.3g}" for k, v in row["GONZALEZ-R"]["parts_us"].items())
            for n, row in results["scaling"]["sizes"].items()), ""]
    lines += ["# Compositions: work against precision", ""] + composition.markdown(results["composition"])
    shard = results["sharding"]
    lines += [f"## Ensemble over {shard['devices']} CPU devices", "",
              f"{shard['batch']} gearbox trajectories x {shard['steps']} GONZALEZ-R steps: one device "
              f"{shard['seconds']['one_device']:.2f} s, {shard['devices']} devices {shard['seconds']['all_devices']:.2f} s, "
              f"speed-up {shard['speedup']:.2f}; largest difference {shard['max_difference']:.1e}.", ""]
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "suite.json"))
    parser.add_argument("--tables-only", action="store_true", help="rewrite the .md tables from the JSON at --out")
    options = parser.parse_args()
    table = pathlib.Path(options.out).with_suffix(".md")
    if options.tables_only:
        table.write_text(markdown(json.loads(pathlib.Path(options.out).read_text())))
        print(table.read_text())
        return
    options.t1 = 100.0 if options.quick else 1000.0
    options.steps = 200 if options.quick else 2000
    options.batch_work = 4000 if options.quick else 40_000
    options.numpy_steps = 20 if options.quick else 200
    options.sharding_steps = 20 if options.quick else 200
    options.scaling_sizes = (1, 3, 10) if options.quick else SCALING_SIZES

    start = time.perf_counter()
    results = dict(h=H, repeats=options.repeats, t1=options.t1, quick=options.quick,
                   methods={}, long_runs={}, equal_wall_time={})
    for name, problem in _problems(max(BATCHES)).items():
        print(f"{name}: nhjax methods", flush=True)
        results["methods"][name] = methods_table(problem, options)
        print(f"{name}: to t = {options.t1:g}", flush=True)
        results["long_runs"][name] = long_runs(problem, options)
        print(f"{name}: equal wall time", flush=True)
        results["equal_wall_time"][name] = equal_wall_time(
            problem, results["long_runs"][name]["GONZALEZ-R"]["seconds"], options
        )
    print("scaling", flush=True)
    results["scaling"] = scaling(options)
    print("sharding", flush=True)
    results["sharding"] = sharding(options)
    print("compositions: work against precision", flush=True)
    results["composition"] = composition.work_precision(options.repeats, options.quick)
    results["suite_seconds"] = time.perf_counter() - start
    write(results, options.out)
    table.write_text(markdown(results))
    print(table.read_text())


if __name__ == "__main__":
    main()
