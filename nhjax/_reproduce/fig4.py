r"""Figure 4 (beyond the paper): work against precision on the chaotic quartic (n = 3,
H = 3.06), from Figure 1's sample state to t = 10.

Every method at a few step sizes: the canonical methods (GONZALEZ-R, GONZALEZ-F, SI-DLA,
I-DLA, SPARK, and Tsit5 at fixed steps on the index-1 ODE), DiscreteGradient with AVF and
Gonzalez on the adapted form, the compositions of order 4, 6 and 8 of GONZALEZ-R and of
Gonzalez on the adapted form (`nhjax.Composition`), the energy-preserving collocations of
order 4 and 6 (`nhjax.EnergyPreservingCollocation`, canonical form), and Dopri8 with adaptive steps over a
range of tolerances, plain and with each step projected onto the energy level and the
constraint (`nhjax.Projection`, energy-exact). Wall time is the median of a few runs after compilation; precision
is the final relative energy error and the error at t = 10 against
`nhjax.integrate_adaptive` at rtol = atol = 1e-13. At each of a few target errors the
report names the cheapest run overall and the cheapest energy-exact run.
"""

import dataclasses

import diffrax
import jax
import jax.numpy as jnp
from tqdm.auto import tqdm

import nhjax as nh

from ._common import (
    check,
    check_run,
    COMPOSITIONS,
    concurrently,
    Context,
    DISCRETE_GRADIENT_METHODS,
    ENERGY_EXACT_METHODS,
    fitted_order,
    median_time,
    METHODS,
    new_figure,
    positive,
    Quartic,
    roundoff,
    run_adaptive,
    run_to,
    save_figure,
    SEED,
    state_error,
    verdict,
)
from ._figure import Figure
from .report import number


FINAL_TIME = 10.0
ADAPTIVE = "Dopri8 (adaptive)"
PROJECTED = "Dopri8 + projection (adaptive)"
_SOLVERS = {ADAPTIVE: diffrax.Dopri8(), PROJECTED: nh.Projection(diffrax.Dopri8())}
# Below this the reference (Dopri8 at 1e-13) and rounding blur the error: the orders of
# the compositions are fitted above it.
ERROR_FLOOR = 1e-11


@dataclasses.dataclass(frozen=True)
class Sizes:
    """- `methods`, `step_sizes`: the fixed-step methods and their step sizes.
    - `compositions`, `composition_step_sizes`: the compositions of order 4, 6 and 8
      (see `_common.COMPOSITIONS`) and their step sizes.
    - `collocations`: the energy-preserving collocations, at the compositions' step
      sizes.
    - `tolerances`: Dopri8's tolerances rtol = atol.
    - `repeats`: how many timed runs the median is taken over.
    - `targets`: the solution errors at which the report names the cheapest runs."""

    methods: tuple[str, ...]
    step_sizes: tuple[float, ...]
    compositions: tuple[str, ...]
    composition_step_sizes: tuple[float, ...]
    collocations: tuple[str, ...]
    tolerances: tuple[float, ...]
    repeats: int
    targets: tuple[float, ...]


FULL = Sizes(
    methods=("GONZALEZ-R", "GONZALEZ-F", "SI-DLA", "I-DLA", "SPARK", "AVF", "GONZALEZ", "Tsit5"),
    # GONZALEZ-F's root find stalls at its tolerance (64 eps) on the quartic at h = 0.00625.
    step_sizes=(0.2, 0.1, 0.05, 0.025, 0.0125),
    compositions=(
        "GONZALEZ-R order 4", "GONZALEZ-R order 6", "GONZALEZ-R order 8",
        "GONZALEZ order 4", "GONZALEZ order 6", "GONZALEZ order 8",
    ),
    composition_step_sizes=(0.5, 0.25, 0.2, 0.125, 0.1, 0.0625, 0.05, 0.025),
    collocations=("EP-COLLOCATION 4", "EP-COLLOCATION 6"),
    tolerances=(1e-4, 1e-6, 1e-8, 1e-10, 1e-12),
    repeats=5,
    targets=(1e-3, 1e-6, 1e-9),
)
# Compilation, not stepping, is most of a quick run: the same programs, fewer repeats.
QUICK = dataclasses.replace(FULL, repeats=3)


def _point(function, outcome, repeats: int, quartic: Quartic, name: str, setting: float, reference, energy0):
    """From the outcome of a first run of `function` (final state, success, steps): wall
    time of `repeats` more, final relative energy error and error at t = 10 of the final
    state (in `name`'s form); `None` if the run failed (a root find not converged), which
    the diagram records rather than stops at."""
    final, succeeded, steps = outcome
    if not bool(succeeded):
        return None
    if name not in _SOLVERS:
        check_run(name, setting, FINAL_TIME, succeeded, steps)
    seconds = median_time(function, repeats)
    canonical = quartic.canonical(name, final) if name in METHODS else final
    return dict(
        wall_time_s=seconds,
        energy_error=float(abs(quartic.energy(canonical) / energy0 - 1)),
        solution_error=state_error(canonical, reference),
        steps=int(steps),
    )


def _run_function(quartic: Quartic, sample, name: str, setting: float):
    """The run of `name` at `setting` (a step size, or Dopri8's tolerance) to t = 10 from
    the sample state, as a call without arguments: one compiled program per method."""
    if name in _SOLVERS:
        y0 = quartic.example.from_adapted(sample)
        return lambda: run_adaptive(
            quartic.example.canonical, y0, jnp.asarray(FINAL_TIME), jnp.asarray(setting), _SOLVERS[name]
        )
    y0 = quartic.start(name, sample)
    return lambda: run_to(quartic.system(name), METHODS[name].solver, y0, jnp.asarray(setting), jnp.asarray(FINAL_TIME))


def measure(context: Context, quartic: Quartic, sample) -> dict:
    """Each method's runs first, methods side by side (`concurrently`: their programs
    compile at once), then every run timed, one at a time."""
    sizes = context.sizes
    reference = quartic.reference(context, FINAL_TIME)
    energy0 = float(quartic.energy(quartic.example.from_adapted(sample)))
    settings = {name: sizes.step_sizes for name in sizes.methods}
    settings |= {name: sizes.composition_step_sizes for name in sizes.compositions + sizes.collocations}
    settings |= {name: sizes.tolerances for name in _SOLVERS}
    functions = {
        name: [_run_function(quartic, sample, name, setting) for setting in values] for name, values in settings.items()
    }
    outcomes = concurrently(
        [lambda runs=runs: [jax.block_until_ready(function()) for function in runs] for runs in functions.values()],
        "Figure 4: first runs (compiling)",
        context.progress,
    )
    runs = [
        (name, setting, function, outcome)
        for (name, values), method_outcomes in zip(settings.items(), outcomes)
        for setting, function, outcome in zip(values, functions[name], method_outcomes)
    ]
    results = {}
    for name, setting, function, outcome in tqdm(runs, desc="Figure 4: timed runs to t = 10", disable=not context.progress):
        point = _point(function, outcome, sizes.repeats, quartic, name, setting, reference, energy0)
        entry = results.setdefault(
            name, dict(settings=[], wall_time_s=[], energy_error=[], solution_error=[], steps=[], failed=[])
        )
        if point is None:
            entry["failed"].append(setting)
            continue
        entry["settings"].append(setting)
        for key, value in point.items():
            entry[key].append(value)
    for name, entry in results.items():
        if name in COMPOSITIONS or name in sizes.collocations:
            entry["fitted_order"] = _asymptotic_order(entry)
        elif name not in _SOLVERS:
            entry["fitted_order"] = (
                fitted_order(entry["settings"], entry["solution_error"]) if len(entry["settings"]) >= 2 else None
            )
    return results


def _asymptotic_order(entry) -> float | None:
    """The order fitted over the three smallest step sizes whose error is above
    `ERROR_FLOOR` (at the largest steps a high-order method is not yet asymptotic)."""
    points = sorted((h, error) for h, error in zip(entry["settings"], entry["solution_error"]) if error > ERROR_FLOOR)
    if len(points) < 2:
        return None
    step_sizes, errors = zip(*points[:3])
    return fitted_order(step_sizes, errors)


def cheapest_at(results, targets) -> dict:
    """For each target solution error: the cheapest run overall and the cheapest
    energy-exact run that reach it (method, setting, wall time), and their ratio."""

    def cheapest(names, target):
        found = [
            dict(method=name, setting=setting, wall_time_s=seconds)
            for name in names
            for setting, seconds, error in zip(
                results[name]["settings"], results[name]["wall_time_s"], results[name]["solution_error"]
            )
            if error <= target
        ]
        return min(found, key=lambda run: run["wall_time_s"]) if found else None

    table = {}
    for target in targets:
        overall = cheapest(list(results), target)
        exact = cheapest([name for name in results if name in ENERGY_EXACT_METHODS or name == PROJECTED], target)
        ratio = exact["wall_time_s"] / overall["wall_time_s"] if overall and exact else None
        table[f"{target:g}"] = dict(overall=overall, energy_exact=exact, energy_exact_over_overall=ratio)
    return table


def plot(path, results) -> str:
    figure, axes = new_figure(2)
    energy_axes, solution_axes = axes[0]
    for name, entry in results.items():
        colour = METHODS[name].colour if name in METHODS else {PROJECTED: "olive"}.get(name, "k")
        style = dict(color=colour, marker="s" if name in _SOLVERS else "o", ms=4, lw=1.0, label=name)
        energy_axes.loglog(entry["wall_time_s"], positive(entry["energy_error"]), **style)
        solution_axes.loglog(entry["wall_time_s"], entry["solution_error"], **style)
    energy_axes.set(xlabel="wall time (s)", ylabel=r"$|H(10)/H(0) - 1|$",
                    title="work against energy error (0 shown at $10^{-18}$)")
    solution_axes.set(xlabel="wall time (s)", ylabel=r"max error at $t = 10$", title="work against solution error")
    return save_figure(figure, path)


def _high_order_checks(results, names, label, bound, bound_formula) -> list[dict]:
    """The energy of the high-order runs `names` (described as `label`) within the
    roundoff `bound`, and each one's fitted order within [p - 0.3, p + 0.6] of its
    method's order p."""
    worst = max((error for name in names for error in results[name]["energy_error"]), default=0.0)
    orders = {name: results[name]["fitted_order"] for name in names}
    expected = {name: METHODS[name].solver.order(None) for name in names}
    return [
        check(worst <= bound, f"energy error of {label} <= {worst:.0e} at every step size",
              f"<= {bound_formula} = {bound:.0e} (roundoff)"),
        check(
            all(order is not None and expected[name] - 0.3 <= order <= expected[name] + 0.6
                for name, order in orders.items()),
            "orders " + ", ".join(f"{name} {order:.2f}" if order is not None else f"{name} not fitted"
                                  for name, order in orders.items())
            + f" (errors above {ERROR_FLOOR:g})",
            "each within [p - 0.3, p + 0.6]",
        ),
    ]


def run(context: Context) -> dict:
    sizes = context.sizes
    quartic = Quartic()
    sample = quartic.ensemble()[0]
    results = measure(context, quartic, sample)
    image = plot(context.out / "fig4.png", results)

    bound = roundoff(round(FINAL_TIME / min(sizes.step_sizes)))
    conserving = [name for name in sizes.methods if name in DISCRETE_GRADIENT_METHODS]
    second_order = [name for name in sizes.methods if name != "Tsit5"]
    compositions = list(sizes.compositions)
    failed = {name: entry["failed"] for name, entry in results.items() if entry["failed"]}
    checks = [check(not failed, "every run succeeded" if not failed else "runs failed: " + "; ".join(
        f"{name} at {', '.join(map(str, settings))}" for name, settings in failed.items()), "no run fails")]
    if conserving:
        worst = max((error for name in conserving for error in results[name]["energy_error"]), default=0.0)
        checks.append(check(worst <= bound, f"energy error of {', '.join(conserving)} <= {worst:.0e} at every step size",
                            f"<= 100 eps sqrt(N) = {bound:.0e} (roundoff)"))
    if second_order:
        orders = {name: results[name]["fitted_order"] for name in second_order}
        checks.append(check(all(order is not None and 1.8 <= order <= 2.2 for order in orders.values()),
                            "orders " + ", ".join(f"{name} {order:.2f}" for name, order in orders.items()
                                                  if order is not None), "each in [1.8, 2.2]"))
    if compositions:
        substeps = max(METHODS[name].solver.stages for name in compositions)
        composition_bound = roundoff(substeps * round(FINAL_TIME / min(sizes.composition_step_sizes)))
        checks += _high_order_checks(
            results, compositions, "the compositions", composition_bound, "100 eps sqrt(substeps)"
        )
    collocations = list(sizes.collocations)
    if collocations:
        collocation_bound = roundoff(round(FINAL_TIME / min(sizes.composition_step_sizes)))
        checks += _high_order_checks(
            results, collocations, "the energy-preserving collocations", collocation_bound, "100 eps sqrt(N)"
        )
    if "Tsit5" in results:
        order = results["Tsit5"]["fitted_order"]
        checks.append(check(order is not None and order > 4, f"Tsit5 order {order or float('nan'):.1f}", "> 4"))
    if PROJECTED in results:
        entry = results[PROJECTED]
        bound_projected = roundoff(max(entry["steps"], default=1))
        worst = max(entry["energy_error"], default=0.0)
        checks.append(check(worst <= bound_projected, f"energy error of {PROJECTED} <= {worst:.0e} at every tolerance",
                            f"<= 100 eps sqrt(steps) = {bound_projected:.0e} (roundoff)"))
    errors = results.get(ADAPTIVE, {}).get("solution_error", [])
    if len(errors) >= 2:
        checks.append(check(errors[-1] < errors[0], f"Dopri8 error {errors[0]:.0e} -> {errors[-1]:.0e} as the tolerance tightens",
                            "the error falls as the tolerance tightens"))
    judged = verdict(checks)
    if judged["agrees"]:
        judged["verdict"] = "Beyond the paper; consistent with Figure 1: " + judged["verdict"][len("Agrees: "):]
    return dict(
        settings=dict(t1=FINAL_TIME, seed=SEED, step_sizes=list(sizes.step_sizes),
                      composition_step_sizes=list(sizes.composition_step_sizes),
                      tolerances=list(sizes.tolerances), repeats=sizes.repeats,
                      timing="median wall time after compilation", roundoff_bound=bound),
        methods=results,
        cheapest_at_solution_error=cheapest_at(results, sizes.targets),
        images=[image],
        checks=checks,
        **judged,
    )


def _cheapest_table(result: dict) -> list[str]:
    """The cheapest runs at each target error, as a table."""

    def described(entry):
        if entry is None:
            return "none reaches it"
        return f"{entry['method']} at {number(entry['setting'])}: {entry['wall_time_s'] * 1e3:.2f} ms"

    lines = [
        "| error at t = 10 | cheapest run | cheapest energy-exact run | ratio |",
        "|---|---|---|---|",
    ]
    for target, row in result["cheapest_at_solution_error"].items():
        ratio = row["energy_exact_over_overall"]
        lines.append(f"| {target} | {described(row['overall'])} | {described(row['energy_exact'])} | "
                     + ("-" if ratio is None else f"{ratio:.2f}") + " |")
    return lines


FIGURE = Figure(
    name="fig4",
    title="Figure 4 (beyond the paper): work against precision on the chaotic quartic",
    run=run,
    full=FULL,
    quick=QUICK,
    columns=("settings", "wall_time_s", "energy_error", "solution_error", "fitted_order"),
    note=(
        "`settings` are the step sizes (Dopri8: the tolerances rtol = atol). Wall times are medians "
        "after compilation, of one trajectory to t = 10 on this machine. Energy-exact runs: the "
        "discrete-gradient methods, their compositions, the energy-preserving collocations, and Dopri8 with each step projected onto "
        "the energy level and the constraint. The ratio is the energy-exact run's time "
        "over the cheapest run's."
    ),
    more_report=_cheapest_table,
)
