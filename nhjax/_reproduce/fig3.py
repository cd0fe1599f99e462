r"""Figure 3 (§4.4): the gearbox driven by an asymmetric pendulum, h = 0.1, to
t = 50 000 (500 000 steps) from a random initial state, with GONZALEZ-R, GONZALEZ-F and
SI-DLA in canonical coordinates: relative energy error and constraint error
$|p_1 + \sin(q_3)p_2|$, saved every 100 steps.

The paper: both Gonzalez methods keep the energy to machine precision, SI-DLA does not;
GONZALEZ-R and SI-DLA keep the constraint, GONZALEZ-F does not. It reports SI-DLA's
energy error growing exponentially for its $H = \tfrac12|p|^2 - V$; with the sign that
makes the oscillators stable (see `nhjax.examples.gearbox`) it stays bounded but far above
roundoff.
"""

import dataclasses

import jax
import numpy as np

import nhjax as nh
from .._runner import run_chunked
from ._figure import Figure
from ._common import check, Context, METHODS, new_figure, positive, roundoff, save_figure, SEED, verdict


STEP = 0.1
NAMES = ("GONZALEZ-R", "GONZALEZ-F", "SI-DLA")


@dataclasses.dataclass(frozen=True)
class Sizes:
    """- `steps`, `save_every`, `chunk_steps`: the run at h = 0.1, its saving interval
    and the steps per chunk on disk."""

    steps: int
    save_every: int
    chunk_steps: int


# t in [0, 50 000] at h = 0.1.
FULL = Sizes(steps=500_000, save_every=100, chunk_steps=50_000)
QUICK = dataclasses.replace(FULL, steps=50_000, chunk_steps=10_000)


def plot(path, runs) -> str:
    figure, axes = new_figure(2)
    energy_axes, constraint_axes = axes[0]
    for name, run in runs.items():
        style = dict(color=METHODS[name].colour, label=name, lw=0.8)
        energy_axes.semilogy(run["times"], positive(run["relative_energy"]), **style)
        constraint_axes.semilogy(run["times"], positive(run["constraint"]), **style)
    energy_axes.set(xlabel="$t$", ylabel=r"$|H(t)/H(0) - 1|$", title="relative energy error")
    constraint_axes.set(xlabel="$t$", ylabel=r"$|p_1 + \sin(q_3)\,p_2|$", title="constraint error")
    return save_figure(figure, path, legend_size=8)


def run(context: Context) -> dict:
    sizes = context.sizes
    gearbox = nh.examples.gearbox()
    y0 = gearbox.random_initial_state(jax.random.key(SEED))
    runs = {}
    for name in NAMES:
        solution = run_chunked(
            gearbox.canonical,
            METHODS[name].solver,
            y0,
            STEP,
            sizes.steps,
            directory=context.chunk_directory(f"fig3_{name}_{sizes.steps}"),
            save_every=sizes.save_every,
            chunk_steps=sizes.chunk_steps,
            progress=context.progress,
        )
        energy = np.asarray(solution.energy)
        runs[name] = dict(
            times=np.asarray(solution.ts),
            relative_energy=np.abs(energy / energy[0] - 1),
            constraint=np.abs(np.asarray(solution.constraint)[:, 0]),
        )
    image = plot(context.out / "fig3.png", runs)

    bound = roundoff(sizes.steps)
    energy = {name: float(run["relative_energy"].max()) for name, run in runs.items()}
    constraint = {name: float(run["constraint"].max()) for name, run in runs.items()}
    checks = [
        check(
            energy["GONZALEZ-R"] <= bound and energy["GONZALEZ-F"] <= bound,
            f"GONZALEZ-R and -F energy error {energy['GONZALEZ-R']:.0e}, {energy['GONZALEZ-F']:.0e}",
            f"both <= 100 eps sqrt(N) = {bound:.0e} (roundoff)",
        ),
        check(energy["SI-DLA"] > 1e3 * bound, f"SI-DLA's energy error {energy['SI-DLA']:.0e}",
              f"> 1000 x {bound:.0e} (not conserved)"),
        check(
            constraint["GONZALEZ-R"] <= bound and constraint["SI-DLA"] <= bound,
            f"GONZALEZ-R and SI-DLA constraint error {constraint['GONZALEZ-R']:.0e}, "
            f"{constraint['SI-DLA']:.0e}",
            f"both <= {bound:.0e} (roundoff)",
        ),
        check(constraint["GONZALEZ-F"] > 1e3 * bound,
              f"GONZALEZ-F's constraint error {constraint['GONZALEZ-F']:.0e}", f"> 1000 x {bound:.0e} (not kept)"),
    ]
    reduced = sizes.steps != FULL.steps
    return dict(
        size_note=(
            f"{sizes.steps} steps (t = {STEP * sizes.steps:g}), not the paper's {FULL.steps} "
            f"(t = {STEP * FULL.steps:g})."
        ) if reduced else None,
        settings=dict(h=STEP, n_steps=sizes.steps, t1=STEP * sizes.steps, seed=SEED,
                      initial_q=np.asarray(y0[0]).tolist(), initial_p=np.asarray(y0[1]).tolist(),
                      save_every=sizes.save_every, roundoff_bound=bound),
        methods={name: dict(max_relative_energy_error=energy[name], max_constraint_error=constraint[name],
                            final_relative_energy_error=float(runs[name]["relative_energy"][-1]))
                 for name in NAMES},
        images=[image],
        checks=checks,
        **verdict(checks),
    )


FIGURE = Figure(
    name="fig3",
    title="Figure 3: the gearbox driven by an asymmetric pendulum (§4.4)",
    run=run,
    full=FULL,
    quick=QUICK,
    columns=("max_relative_energy_error", "final_relative_energy_error", "max_constraint_error"),
    note="Errors are maxima over the saves (every 100 steps).",
)
