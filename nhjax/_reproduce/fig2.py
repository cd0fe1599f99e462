r"""Figure 2 (§4.2): the Chaplygin sleigh, J = 8, a = m = 1, h = 0.5, from
$x_1 = -5$, $x_2 = 0$, $\theta = 0.1$, $\rho_2 = -0.6$ and $\rho_1 = \pm 0.001$: next to
the unstable equilibrium $(0, -0.6)$.

The method of the paper, (ChapEq), is DiscreteGradient with the Gonzalez discrete
gradient on the adapted equations. Proposition 4.1: its equilibria are $\rho_1 = 0$,
stable for $\rho_2 > 0$ and unstable for $\rho_2 < 0$ when $h < |2/(C^1_{12}\rho_2)|$;
with the energy $\tfrac12(\rho_1^2 + \rho_2^2)$ conserved, both paths must settle at
$\rho_1 = 0$, $\rho_2 = +\sqrt{\rho_1^2 + \rho_2^2}$. GONZALEZ-R on the canonical sleigh
runs beside it (its reduced coordinates come from a Householder frame, not the paper's;
its paths are shown in the paper's $\rho$ through `to_adapted`).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

import nhjax as nh
from ._common import check, Context, METHODS, new_figure, roundoff, save_figure, verdict
from ._figure import Figure


STEP = 0.5
RHO1 = (-0.001, 0.001)
RHO2 = -0.6
# The x1x2 panel shows the turn from the unstable to the stable motion; after it the
# sleigh runs straight on.
PARTIAL_TIME = 250.0


@dataclasses.dataclass(frozen=True)
class Sizes:
    """- `steps`: the steps of h = 0.5.
    - `gonzalez_r`: whether GONZALEZ-R on the canonical sleigh runs beside the adapted
      method."""

    steps: int
    gonzalez_r: bool


FULL = Sizes(steps=2000, gonzalez_r=True)
# GONZALEZ-R on the sleigh alone compiles for longer than the rest of the figure.
QUICK = dataclasses.replace(FULL, gonzalez_r=False)


def _paths(sleigh, method_name: str, starts, n_steps: int):
    """Both trajectories of `method_name` (every step saved) as adapted states, with the
    canonical constraint residual |A(q) M^-1 p| at each."""
    method = METHODS[method_name]
    if method.adapted:
        system, y0 = sleigh.adapted, starts
    else:
        system, y0 = sleigh.canonical, jax.vmap(lambda x: sleigh.from_adapted(x))(starts)

    def run(y):
        return nh.integrate(system, method.solver, y, STEP, n_steps, args=sleigh.args)

    solution = jax.vmap(run)(y0)
    if method.adapted:
        adapted = solution.ys
        canonical = jax.vmap(jax.vmap(lambda x: sleigh.from_adapted(x)))(adapted)
    else:
        canonical = solution.ys
        adapted = jax.vmap(jax.vmap(lambda q, p: sleigh.to_adapted(q, p)))(*canonical)
    residual = jax.vmap(jax.vmap(lambda q, p: sleigh.canonical.constraint_residual((q, p), sleigh.args)))(*canonical)
    return (
        np.asarray(solution.ts[0]),
        np.asarray(adapted),
        np.asarray(solution.energy),
        float(jnp.max(jnp.abs(residual))),
    )


def plot(path, paths, settled_rho2) -> str:
    figure, axes = new_figure(2)
    position_axes, momentum_axes = axes[0]
    for name, (times, adapted, _, _) in paths.items():
        partial = times <= PARTIAL_TIME
        for index, rho1 in enumerate(RHO1):
            style = dict(color=METHODS[name].colour, ls="-" if index else ":", lw=1.0)
            label = f"{name}, $\\rho_1(0) = {rho1}$"
            position_axes.plot(adapted[index, partial, 0], adapted[index, partial, 1], label=label, **style)
            momentum_axes.plot(adapted[index, :, 3], adapted[index, :, 4], ".", ms=2, label=label, **style)
    momentum_axes.plot([0, 0], [RHO2, settled_rho2], "kx", label="equilibria: start (unstable), end (stable)")
    position_axes.set(xlabel="$x_1$", ylabel="$x_2$", title=f"$x_1x_2$ paths to $t = {PARTIAL_TIME:g}$")
    momentum_axes.set(xlabel=r"$\rho_1$", ylabel=r"$\rho_2$", title=r"$\rho_1\rho_2$ paths")
    return save_figure(figure, path)


def run(context: Context) -> dict:
    sizes = context.sizes
    sleigh = nh.examples.chaplygin_sleigh(J=8.0, a=1.0, m=1.0)
    starts = jnp.stack([sleigh.initial_state(x1=-5.0, x2=0.0, theta=0.1, rho1=rho1, rho2=RHO2) for rho1 in RHO1])
    names = ("GONZALEZ", "GONZALEZ-R") if sizes.gonzalez_r else ("GONZALEZ",)
    paths = {name: _paths(sleigh, name, starts, sizes.steps) for name in names}
    settled_rho2 = float(np.hypot(RHO1[1], RHO2))
    image = plot(context.out / "fig2.png", paths, settled_rho2)

    stability_limit = float(abs(2 / (sleigh.bracket_coefficient(sleigh.args) * RHO2)))
    bound = roundoff(sizes.steps)
    per_method, checks = {}, []
    for name, (times, adapted, energy, constraint) in paths.items():
        final = adapted[:, -1, 3:]
        crossing = [float(times[np.argmax(path[:, 4] > 0)]) for path in adapted]
        energy_error = float(np.max(np.abs(energy / energy[:, :1] - 1)))
        per_method[name] = dict(
            final_rho=final.tolist(),
            max_abs_final_rho1=float(np.max(np.abs(final[:, 0]))),
            max_final_rho2_error=float(np.max(np.abs(final[:, 1] - settled_rho2))),
            time_rho2_turns_positive=crossing,
            max_relative_energy_error=energy_error,
            max_constraint_error=constraint,
        )
        result = per_method[name]
        checks += [
            check(
                result["max_abs_final_rho1"] < 1e-8 and result["max_final_rho2_error"] < bound,
                f"{name} settles at rho = (0, {settled_rho2:.10f}) from both sides: |rho1| "
                f"{result['max_abs_final_rho1']:.0e}, rho2 off by {result['max_final_rho2_error']:.0e}",
                f"|rho1| < 1e-8 and |rho2 - {settled_rho2:.10f}| <= 100 eps sqrt(N) = {bound:.0e}",
            ),
            check(energy_error <= bound and constraint <= bound,
                  f"{name} energy error {energy_error:.0e}, constraint {constraint:.0e}",
                  f"both <= {bound:.0e} (roundoff)"),
        ]
    checks.append(check(STEP < stability_limit, f"h = {STEP}, |2/(C rho2)| = {stability_limit:.1f}",
                        "h < |2/(C rho2)| (Proposition 4.1)"))
    return dict(
        settings=dict(J=8.0, a=1.0, m=1.0, h=STEP, n_steps=sizes.steps, x1=-5.0, x2=0.0, theta=0.1,
                      rho1=list(RHO1), rho2=RHO2, stability_limit_h=stability_limit, roundoff_bound=bound),
        expected_final_rho=[0.0, settled_rho2],
        methods=per_method,
        images=[image],
        checks=checks,
        **verdict(checks),
    )


FIGURE = Figure(
    name="fig2",
    title="Figure 2: the Chaplygin sleigh (§4.2)",
    run=run,
    full=FULL,
    quick=QUICK,
    columns=("final_rho", "time_rho2_turns_positive", "max_relative_energy_error", "max_constraint_error"),
    note="rho = (rho1, rho2) in the paper's orthonormal frame, for rho1(0) = -0.001 and 0.001.",
)
