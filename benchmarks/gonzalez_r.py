"""GONZALEZ-R on the gearbox (h = 0.1) and on the n = 3 chaotic quartic.

Measures, in one run: µs/step for one gearbox trajectory; the paper's full gearbox run
(t in [0, 50000], 500 000 steps) after compilation; compile time; trajectory-steps/s for
a vmapped batch of gearbox trajectories; and on the quartic, GONZALEZ-R on the canonical
system against DiscreteGradient on the analytic reduced form (the ratio of µs/step).
GONZALEZ-F is timed beside it for reference.

Run: python benchmarks/gonzalez_r.py [--steps N] [--repeats R]
Figures are medians over repeats; results go to benchmarks/results/gonzalez_r.json.
"""

import argparse
import pathlib

import jax


jax.config.update("jax_enable_x64", True)

import nhjax as nh  # noqa: E402
from _timing import per_step, run_and_time, timed, write  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--long-steps", type=int, default=500_000)
    parser.add_argument("--batch-steps", type=int, default=500)
    parser.add_argument("--batch", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "gonzalez_r.json"))
    options = parser.parse_args()

    gearbox = nh.examples.gearbox()
    y0 = gearbox.random_initial_state(jax.random.key(0))
    method = nh.GonzalezR()

    single_us, compile_s, iterations = per_step(gearbox.canonical, method, y0, options.steps, options.repeats)
    finite_us, finite_compile_s, finite_iterations = per_step(
        gearbox.canonical, nh.GonzalezR(derivative="central_difference"), y0, options.steps, options.repeats
    )
    direct_us, direct_compile_s, direct_iterations = per_step(
        gearbox.canonical, nh.GonzalezF(), y0, options.steps, options.repeats
    )

    long_run = jax.jit(
        lambda y0: nh.integrate(gearbox.canonical, method, y0, 0.1, options.long_steps, save_every=1000)
    )
    long_run = long_run.lower(y0).compile()
    long_solution, long_seconds = run_and_time(long_run, y0, repeats=max(1, options.repeats // 2))
    long_energy = float(abs(long_solution.energy / long_solution.energy[0] - 1).max())
    long_constraint = float(abs(long_solution.constraint).max())

    states = jax.vmap(gearbox.random_initial_state)(jax.random.split(jax.random.key(1), options.batch))
    batch = jax.jit(jax.vmap(
        lambda y0: nh.integrate(gearbox.canonical, method, y0, 0.1, options.batch_steps, save_every=options.batch_steps).ys
    ))
    batch_compile_s = timed(lambda y: batch.lower(y).compile(), states)
    _, batch_seconds = run_and_time(batch, states, repeats=options.repeats)
    batch_rate = options.batch * options.batch_steps / batch_seconds

    quartic = nh.examples.chaotic_quartic(3)
    x0 = quartic.initial_state(0.7)
    quartic_r_us, quartic_r_compile_s, _ = per_step(
        quartic.canonical, method, quartic.from_adapted(x0), options.steps // 4, options.repeats
    )
    quartic_dg_us, quartic_dg_compile_s, _ = per_step(
        quartic.adapted, nh.DiscreteGradient(), x0, options.steps // 4, options.repeats
    )

    results = dict(
        h=0.1,
        gearbox=dict(
            gonzalez_r=dict(
                us_per_step=single_us, target_us_per_step=10.0, compile_s=compile_s, target_compile_s=15.0,
                root_find_iterations_per_step=iterations,
            ),
            gonzalez_r_central_difference=dict(
                us_per_step=finite_us, compile_s=finite_compile_s, root_find_iterations_per_step=finite_iterations
            ),
            gonzalez_f=dict(
                us_per_step=direct_us, compile_s=direct_compile_s, root_find_iterations_per_step=direct_iterations
            ),
            full_run=dict(
                steps=options.long_steps, seconds=long_seconds, target_seconds=10.0,
                max_relative_energy_error=long_energy, max_constraint_error=long_constraint,
            ),
            batch=dict(
                trajectories=options.batch, steps=options.batch_steps, trajectory_steps_per_s=batch_rate,
                target_trajectory_steps_per_s=5e5, compile_s=batch_compile_s,
            ),
        ),
        quartic_n3=dict(
            gonzalez_r_us_per_step=quartic_r_us,
            discrete_gradient_reduced_us_per_step=quartic_dg_us,
            ratio=quartic_r_us / quartic_dg_us,
            target_ratio=3.0,
            compile_s=dict(gonzalez_r=quartic_r_compile_s, discrete_gradient=quartic_dg_compile_s),
        ),
        repeats=options.repeats,
    )
    print(f"gearbox GONZALEZ-R      : {single_us:8.2f} µs/step, {iterations:.2f} iterations/step  (target <= 10)")
    print(f"   central differences  : {finite_us:8.2f} µs/step")
    print(f"gearbox GONZALEZ-F      : {direct_us:8.2f} µs/step")
    print(f"compile GONZALEZ-R      : {compile_s:8.2f} s  (target <= 15)")
    print(f"full run, {options.long_steps} steps: {long_seconds:8.2f} s  (target < 10); "
          f"energy {long_energy:.1e}, constraint {long_constraint:.1e}")
    print(f"batch of {options.batch}           : {batch_rate:10.3e} trajectory-steps/s  (target >= 5e5)")
    print(f"quartic n = 3           : GONZALEZ-R {quartic_r_us:.2f} µs/step, reduced DiscreteGradient "
          f"{quartic_dg_us:.2f} µs/step, ratio {quartic_r_us / quartic_dg_us:.2f}  (target <= 3)")
    write(results, options.out)


if __name__ == "__main__":
    main()
