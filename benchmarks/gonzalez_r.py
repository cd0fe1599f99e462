"""GONZALEZ-R's speed against the yardsticks, all timed in one process.

- One gearbox trajectory (h = 0.1): µs/step against the implicit-midpoint yardstick
  (`_timing.yardstick`), target at most 2.5x; GONZALEZ-R with central differences and
  GONZALEZ-F beside it.
- The n = 3 chaotic quartic: GONZALEZ-R on the canonical system against
  DiscreteGradient on the analytic reduced form, target at most 3x.
- Both against GONZALEZ-R in NumPy with one `scipy.optimize.fsolve` per step
  (`peers.py`), timed in each round right after the JAX run, target at least 100x
  faster.
- A vmapped batch of 200 gearbox trajectories: trajectory-steps/s against the vmapped
  yardstick, target at most 2x slower, and no trajectory failing; the quartic batch
  beside it.
- What `nhjax.integrate`'s loop adds: the gearbox steps strung together by a bare `lax.scan`.
- Compile times, root-finder iterations per step, and the paper's full gearbox run
  (t in [0, 50000], 500 000 steps) with its energy and constraint errors.

Each yardstick is timed right before the run it is compared with, and the pair is
measured `--rounds` times; ratios are the medians over the rounds.

Run: python benchmarks/gonzalez_r.py [--steps N] [--repeats R] [--rounds K]
Results go to benchmarks/results/gonzalez_r.json.
"""

import statistics

import jax
import numpy as np


jax.config.update("jax_enable_x64", True)

import nhjax as nh  # noqa: E402
import peers  # noqa: E402
from _timing import bare_loop_per_step, batch_rate, options as command_line, per_step, run_and_time, timed, write, yardstick  # noqa: E402


def _median_ratio(pairs):
    return statistics.median(a / b for a, b in pairs)


def main():
    options = command_line(
        __doc__,
        "gonzalez_r",
        steps=20_000,
        long_steps=500_000,
        batch_steps=500,
        batch=200,
        numpy_steps=200,
        repeats=5,
        rounds=3,
    )

    gearbox = nh.examples.gearbox()
    y0 = gearbox.random_initial_state(jax.random.key(0))
    method = nh.GonzalezR()
    quartic = nh.examples.chaotic_quartic(3)
    x0 = quartic.initial_state(0.7)
    quartic_y0 = quartic.from_adapted(x0)
    quartic_steps = options.steps // 4

    single, quartic_pairs, batch_pairs = [], [], []
    numpy_pairs = dict(gearbox=[], quartic_n3=[])
    numpy_starts = dict(gearbox=(peers.GEARBOX, y0), quartic_n3=(peers.QUARTIC3, quartic_y0))

    def numpy_us_per_step(name):
        problem, start = numpy_starts[name]
        q0, p0 = (np.asarray(leaf) for leaf in start)
        return statistics.median(
            peers.gonzalez_r_numpy(problem, q0, p0, 0.1, options.numpy_steps)["seconds"] / options.numpy_steps * 1e6
            for _ in range(max(1, options.repeats // 2))
        )

    gearbox_states = jax.vmap(gearbox.random_initial_state)(jax.random.split(jax.random.key(1), options.batch))
    for _ in range(options.rounds):
        yard_us = yardstick(options.steps, options.repeats)
        gr_us, compile_s, iterations = per_step(gearbox.canonical, method, y0, options.steps, options.repeats)
        single.append((gr_us, yard_us))
        numpy_pairs["gearbox"].append((numpy_us_per_step("gearbox"), gr_us))
        dg_us, dg_compile_s, dg_iterations = per_step(
            quartic.adapted, nh.DiscreteGradient(), x0, quartic_steps, options.repeats
        )
        quartic_us, quartic_compile_s, quartic_iterations = per_step(
            quartic.canonical, method, quartic_y0, quartic_steps, options.repeats
        )
        quartic_pairs.append((quartic_us, dg_us))
        numpy_pairs["quartic_n3"].append((numpy_us_per_step("quartic_n3"), quartic_us))
        yard_rate = yardstick(options.batch_steps, options.repeats, batch=options.batch)
        gr_rate, failed = batch_rate(gearbox.canonical, method, gearbox_states, options.batch_steps, options.repeats)
        batch_pairs.append((yard_rate, gr_rate))
        print(f"round: gearbox {gr_us:.2f} µs/step, yardstick {yard_us:.2f} ({gr_us / yard_us:.2f}x); "
              f"quartic {quartic_us:.2f} against DiscreteGradient {dg_us:.2f} ({quartic_us / dg_us:.2f}x); "
              f"batch {gr_rate:.3e} against {yard_rate:.3e} ({yard_rate / gr_rate:.2f}x slower), {failed} failed; "
              f"NumPy + fsolve {_median_ratio(numpy_pairs['gearbox'][-1:]):.0f}x and "
              f"{_median_ratio(numpy_pairs['quartic_n3'][-1:]):.0f}x slower")

    bare_us = bare_loop_per_step(gearbox.canonical, method, y0, options.steps, options.repeats)
    finite_us, finite_compile_s, finite_iterations = per_step(
        gearbox.canonical, nh.GonzalezR(derivative="central_difference"), y0, options.steps, options.repeats
    )
    direct_us, direct_compile_s, direct_iterations = per_step(
        gearbox.canonical, nh.GonzalezF(), y0, options.steps, options.repeats
    )

    quartic_batch = jax.vmap(lambda key: quartic.from_adapted(quartic.initial_state(0.7) + 0.01 * jax.random.normal(
        key, x0.shape, x0.dtype)))(jax.random.split(jax.random.key(2), options.batch))
    quartic_rate, quartic_failed = batch_rate(
        quartic.canonical, method, quartic_batch, options.batch_steps, options.repeats
    )

    long_run = jax.jit(
        lambda y0: nh.integrate(gearbox.canonical, method, y0, 0.1, options.long_steps, save_every=1000)
    )
    long_run = long_run.lower(y0).compile()
    long_solution, long_seconds = run_and_time(long_run, y0, repeats=max(1, options.repeats // 2))
    long_energy = float(abs(long_solution.energy / long_solution.energy[0] - 1).max())
    long_constraint = float(abs(long_solution.constraint).max())
    batch_compile_s = timed(
        lambda y: jax.jit(jax.vmap(lambda y0: nh.integrate(
            gearbox.canonical, method, y0, 0.1, options.batch_steps, save_every=options.batch_steps).ys
        )).lower(y).compile(),
        gearbox_states,
    )

    gr_us = statistics.median(a for a, _ in single)
    quartic_us = statistics.median(a for a, _ in quartic_pairs)
    results = dict(
        h=0.1,
        gearbox=dict(
            gonzalez_r=dict(
                us_per_step=gr_us, yardstick_us_per_step=statistics.median(b for _, b in single),
                ratio_to_yardstick=_median_ratio(single), target_ratio=2.5,
                numpy_fsolve_us_per_step=statistics.median(a for a, _ in numpy_pairs["gearbox"]),
                numpy_speedup=_median_ratio(numpy_pairs["gearbox"]),
                target_numpy_speedup=100.0,
                compile_s=compile_s, root_find_iterations_per_step=iterations,
                bare_scan_us_per_step=bare_us,
            ),
            gonzalez_r_central_difference=dict(
                us_per_step=finite_us, compile_s=finite_compile_s, root_find_iterations_per_step=finite_iterations
            ),
            gonzalez_f=dict(
                us_per_step=direct_us, compile_s=direct_compile_s, root_find_iterations_per_step=direct_iterations
            ),
            batch=dict(
                trajectories=options.batch, steps=options.batch_steps,
                trajectory_steps_per_s=statistics.median(b for _, b in batch_pairs),
                yardstick_trajectory_steps_per_s=statistics.median(a for a, _ in batch_pairs),
                slowdown_to_yardstick=_median_ratio(batch_pairs), target_slowdown=2.0,
                failed_trajectories=failed, compile_s=batch_compile_s,
            ),
            full_run=dict(
                steps=options.long_steps, seconds=long_seconds,
                max_relative_energy_error=long_energy, max_constraint_error=long_constraint,
            ),
        ),
        quartic_n3=dict(
            gonzalez_r_us_per_step=quartic_us,
            discrete_gradient_reduced_us_per_step=statistics.median(b for _, b in quartic_pairs),
            ratio=_median_ratio(quartic_pairs), target_ratio=3.0,
            numpy_fsolve_us_per_step=statistics.median(a for a, _ in numpy_pairs["quartic_n3"]),
            numpy_speedup=_median_ratio(numpy_pairs["quartic_n3"]),
            root_find_iterations_per_step=dict(gonzalez_r=quartic_iterations, discrete_gradient=dg_iterations),
            compile_s=dict(gonzalez_r=quartic_compile_s, discrete_gradient=dg_compile_s),
            batch=dict(trajectories=options.batch, trajectory_steps_per_s=quartic_rate, failed_trajectories=quartic_failed),
        ),
        repeats=options.repeats,
        rounds=options.rounds,
    )
    gearbox_results, quartic_results = results["gearbox"], results["quartic_n3"]
    print(f"gearbox GONZALEZ-R : {gr_us:.2f} µs/step, {gearbox_results['gonzalez_r']['ratio_to_yardstick']:.2f}x "
          f"the yardstick (target <= 2.5), {gearbox_results['gonzalez_r']['numpy_speedup']:.0f}x NumPy + fsolve "
          f"(target >= 100), {iterations:.2f} iterations/step, compile {compile_s:.1f} s")
    print(f"   the same steps in a bare lax.scan, without nh.integrate's loop: {bare_us:.2f} µs/step")
    print(f"   central differences {finite_us:.2f} µs/step; GONZALEZ-F {direct_us:.2f} µs/step")
    print(f"quartic n = 3      : {quartic_us:.2f} µs/step, {quartic_results['ratio']:.2f}x DiscreteGradient on the "
          f"reduced form (target <= 3), {quartic_results['numpy_speedup']:.0f}x NumPy + fsolve (target >= 100)")
    print(f"batch of {options.batch}      : gearbox {gearbox_results['batch']['trajectory_steps_per_s']:.3e} "
          f"trajectory-steps/s, {gearbox_results['batch']['slowdown_to_yardstick']:.2f}x slower than the yardstick "
          f"(target <= 2), {failed} failed; quartic {quartic_rate:.3e}, {quartic_failed} failed")
    print(f"full run, {options.long_steps} steps: {long_seconds:.2f} s; energy {long_energy:.1e}, "
          f"constraint {long_constraint:.1e}")
    write(results, options.out)


if __name__ == "__main__":
    main()
