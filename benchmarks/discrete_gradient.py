"""DiscreteGradient on the reduced chaotic quartic (n = 3, h = 0.1): µs/step for one
trajectory, trajectory-steps/s for a vmapped batch of 200, and compile time.

Run: python benchmarks/discrete_gradient.py [--steps N] [--repeats R]
Figures are medians over repeats; results go to benchmarks/results/discrete_gradient.json.
"""


import jax


jax.config.update("jax_enable_x64", True)


import nhjax as nh  # noqa: E402
from _timing import options as command_line, run_and_time, timed, write  # noqa: E402


def main():
    options = command_line(
        __doc__, "discrete_gradient", steps=20_000, batch_steps=2_000, batch=200, repeats=5
    )

    quartic = nh.examples.chaotic_quartic(3)
    method = nh.DiscreteGradient()
    h = 0.1

    single = jax.jit(lambda x0: nh.integrate(quartic.adapted, method, x0, h, options.steps, save_every=options.steps).ys)
    batch = jax.jit(jax.vmap(
        lambda x0: nh.integrate(quartic.adapted, method, x0, h, options.batch_steps, save_every=options.batch_steps).ys
    ))
    x0 = quartic.initial_state(0.7)
    states = quartic.random_initial_states(jax.random.key(0), options.batch)

    compile_single = timed(lambda x: single.lower(x).compile(), x0)
    compile_batch = timed(lambda x: batch.lower(x).compile(), states)
    _, single_seconds = run_and_time(single, x0, repeats=options.repeats)
    _, batch_seconds = run_and_time(batch, states, repeats=options.repeats)
    us_per_step = single_seconds / options.steps * 1e6
    batch_rate = options.batch * options.batch_steps / batch_seconds
    iterations = nh.integrate(quartic.adapted, method, x0, h, options.steps, save_every=options.steps).stats
    results = dict(
        system="chaotic quartic, adapted (n = 3, N = 13)",
        method="DiscreteGradient(gonzalez), midpoint structure, Newton",
        h=h,
        single=dict(steps=options.steps, us_per_step=us_per_step, target_us_per_step=5.0),
        batch=dict(
            trajectories=options.batch,
            steps=options.batch_steps,
            trajectory_steps_per_s=batch_rate,
            target_trajectory_steps_per_s=1e6,
        ),
        compile_s=dict(single=compile_single, batch=compile_batch, target=10.0),
        root_find_iterations_per_step=float(iterations["root_find_steps"]) / options.steps,
        repeats=options.repeats,
    )
    print(f"single trajectory : {us_per_step:8.2f} µs/step  (target <= 5)")
    print(f"batch of {options.batch:<8} : {batch_rate:10.3e} trajectory-steps/s  (target >= 1e6)")
    print(f"compile           : {compile_single:.2f} s single, {compile_batch:.2f} s batch  (target <= 10)")
    print(f"chord iterations  : {results['root_find_iterations_per_step']:.2f} per step")
    write(results, options.out)


if __name__ == "__main__":
    main()
