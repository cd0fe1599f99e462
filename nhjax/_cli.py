"""The `nhjax` command."""

import argparse
import sys
import time


def _demo(arguments) -> int:
    """Integrate the Chaplygin sleigh of Figure 2 and report what is conserved."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import nhjax as nh

    sleigh = nh.examples.chaplygin_sleigh(J=8.0, a=1.0, m=1.0)
    x0 = sleigh.initial_state(x1=-5.0, x2=0.0, theta=0.1, rho1=0.001, rho2=-0.6)
    start = time.perf_counter()
    solution = nh.integrate(
        sleigh.adapted, nh.DiscreteGradient(), x0, dt=arguments.dt, n_steps=arguments.steps,
        args=sleigh.args, progress=arguments.progress,
    )
    jax.block_until_ready(solution.ys)
    elapsed = time.perf_counter() - start

    discrete = nh.examples.discrete_constraint_residual(sleigh.constraints, solution.ys[:, :3], sleigh.args)

    def canonical_residual(x):
        q, p = sleigh.from_adapted(x)
        return sleigh.constraints(q, sleigh.args) @ jnp.linalg.solve(sleigh.metric(q, sleigh.args), p)

    canonical = jax.vmap(canonical_residual)(solution.ys)
    energy_error = jnp.max(jnp.abs(solution.energy / solution.energy[0] - 1))
    rho_final = solution.ys[-1, 3:]
    print("Chaplygin sleigh (paper §4.2, Figure 2): J = 8, a = m = 1,")
    print(f"  h = {arguments.dt}, {arguments.steps} steps of DiscreteGradient(gonzalez), from rho = (0.001, -0.6)")
    print(f"  max relative energy error          {float(energy_error):.2e}")
    print(f"  max discrete constraint residual   {float(jnp.max(jnp.abs(discrete))):.2e}")
    print(f"  max constraint residual A(q) qdot  {float(jnp.max(jnp.abs(canonical))):.2e}")
    print(f"  final (rho1, rho2) = ({float(rho_final[0]):.3e}, {float(rho_final[1]):.12f})"
          f"  [Proposition 4.1: -> (0, {float(jnp.hypot(0.001, 0.6)):.12f})]")
    print(f"  root-finder iterations per step    {float(solution.stats['root_find_steps']) / arguments.steps:.2f}")
    print(f"  wall time (with compilation)       {elapsed:.2f} s")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="nhjax",
        description="Energy- and constraint-preserving integrators for nonholonomic systems.",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser(
        "demo", help="integrate the Chaplygin sleigh and print its energy and constraint errors"
    )
    demo.add_argument("--dt", type=float, default=0.5, help="step size h (default 0.5, as in Figure 2)")
    demo.add_argument("--steps", type=int, default=2000, help="number of steps (default 2000)")
    demo.add_argument("--progress", action="store_true", help="show a progress bar")
    arguments = parser.parse_args(argv)
    if arguments.dt <= 0:
        parser.error(f"--dt must be positive, got {arguments.dt}")
    if arguments.steps < 1:
        parser.error(f"--steps must be a positive integer, got {arguments.steps}")
    return _demo(arguments)


if __name__ == "__main__":
    sys.exit(main())
