"""DiscreteGradient on the reduced chaotic quartic (n = 3, h = 0.1), with the Gonzalez and
the AVF discrete gradients: µs/step for one trajectory, trajectory-steps/s for a vmapped
batch of 200, compile time and chord iterations per step.

The AVF runs are timed in turns with AVF whose chord matrix is the Jacobian of its
residual itself (`"avf, exact chord matrix"`, what nhjax formed before its chord matrix
took the midpoint gradient, `nhjax.DiscreteGradient.simplified_residual`), and the
ratios of the two are reported.

Run: python benchmarks/discrete_gradient.py [--steps N] [--repeats R]
Figures are medians over repeats; results go to benchmarks/results/discrete_gradient.json.
"""


import jax


jax.config.update("jax_enable_x64", True)


import nhjax as nh  # noqa: E402
from _timing import options as command_line, run_and_time_interleaved, timed, write  # noqa: E402


class _AVFWithExactChordMatrix(nh.DiscreteGradient):
    """AVF whose chord matrix is the Jacobian of the residual itself, quadrature and all."""

    def simplified_residual(self, u, data):
        return self.residual(u, data)


# The targets set for a discrete-gradient step, per method.
TARGETS = dict(us_per_step=5.0, trajectory_steps_per_s=1e6, compile_s=10.0)

METHODS = {
    "gonzalez": nh.DiscreteGradient(),
    "avf": nh.DiscreteGradient(nh.avf),
    "avf, exact chord matrix": _AVFWithExactChordMatrix(nh.avf),
}


def main():
    options = command_line(
        __doc__, "discrete_gradient", steps=20_000, batch_steps=2_000, batch=200, repeats=5
    )

    quartic = nh.examples.chaotic_quartic(3)
    h = 0.1
    x0 = quartic.initial_state(0.7)
    states = quartic.random_initial_states(jax.random.key(0), options.batch)

    singles, batches, compiled = {}, {}, {}
    for name, method in METHODS.items():
        singles[name] = jax.jit(
            lambda x, method=method: nh.integrate(
                quartic.adapted, method, x, h, options.steps, save_every=options.steps
            )
        )
        batches[name] = jax.jit(jax.vmap(
            lambda x, method=method: nh.integrate(
                quartic.adapted, method, x, h, options.batch_steps, save_every=options.batch_steps
            ).ys
        ))
        compiled[name] = dict(
            single=timed(lambda x: singles[name].lower(x).compile(), x0),
            batch=timed(lambda x: batches[name].lower(x).compile(), states),
        )
    single_outputs, single_seconds = run_and_time_interleaved(singles, x0, repeats=options.repeats)
    _, batch_seconds = run_and_time_interleaved(batches, states, repeats=options.repeats)

    results = dict(
        system="chaotic quartic, adapted (n = 3, N = 13)", h=h, repeats=options.repeats, targets=TARGETS, methods={}
    )
    for name in METHODS:
        iterations = float(single_outputs[name].stats["root_find_steps"]) / options.steps
        results["methods"][name] = dict(
            single=dict(steps=options.steps, us_per_step=single_seconds[name] / options.steps * 1e6),
            batch=dict(
                trajectories=options.batch,
                steps=options.batch_steps,
                trajectory_steps_per_s=options.batch * options.batch_steps / batch_seconds[name],
            ),
            compile_s=compiled[name],
            root_find_iterations_per_step=iterations,
        )
        print(f"{name:24s}: {single_seconds[name] / options.steps * 1e6:8.2f} µs/step single, "
              f"{options.batch * options.batch_steps / batch_seconds[name]:10.3e} trajectory-steps/s in a batch "
              f"of {options.batch}, compiled in {compiled[name]['single']:.2f} s / {compiled[name]['batch']:.2f} s, "
              f"{iterations:.2f} chord iterations per step")
    print(f"targets: <= {TARGETS['us_per_step']:g} µs/step single, >= {TARGETS['trajectory_steps_per_s']:.0e} "
          f"trajectory-steps/s in a batch, compiled in <= {TARGETS['compile_s']:g} s")
    exact = "avf, exact chord matrix"
    results["avf_over_exact_chord_matrix"] = dict(
        single=single_seconds["avf"] / single_seconds[exact],
        batch=batch_seconds["avf"] / batch_seconds[exact],
        compile_single=compiled["avf"]["single"] / compiled[exact]["single"],
    )
    print("avf over its exact chord matrix, time: "
          + ", ".join(f"{key} {value:.2f}" for key, value in results["avf_over_exact_chord_matrix"].items()))
    write(results, options.out)


if __name__ == "__main__":
    main()
