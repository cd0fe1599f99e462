"""Work against precision with compositions: how cheaply an energy-exact nhjax run reaches
a solution error, against Dopri8 with adaptive steps, both timed in this process.

Problems: the n = 3 chaotic quartic (from the state of angle 0.7) and the gearbox (random
state of key 0), to t = 10. Runs:

- energy-exact: GONZALEZ-R and its compositions of order 4, 6 and 8 (`nhjax.Composition`)
  in canonical coordinates; on the quartic also DiscreteGradient(gonzalez) and its
  compositions on the reduced form (errors measured on (q, p) after mapping back);
- energy-exact and symmetric in one solve a step: `nhjax.EnergyPreservingCollocation` of
  every order from 4 to 12 in canonical coordinates (through the reduced form), with its chord
  matrix formed at every step and kept from step to step (`reuse_chord_matrix=True`);
- energy-exact too, not symmetric: Dopri8 with adaptive steps, each step projected onto
  the energy level and the constraint (`nhjax.Projection`), over a sweep of tolerances;
- Tsit5 at fixed steps, and Dopri8 with adaptive steps (`nhjax.integrate_adaptive`'s
  solver) over a sweep of tolerances.

Fixed-step runs use step sizes t1/N for a geometric sequence of N (one compilation per
method: the step size is traced). Each time is the median of `--repeats` timings after a
warm-up. Error: max-norm distance at t = 10 to a reference, Dopri8 at rtol = atol = 1e-15
(its distance to the order-8 composition at the smallest step is reported).

For each target error (1e-3, 1e-6, 1e-8, 1e-9, 1e-10): the cheapest run overall, the
cheapest energy-exact run, the cheapest symmetric energy-exact run and the cheapest
Dopri8 run that reach it, the ratios of the energy-exact and symmetric times to
Dopri8's, every symmetric energy-exact method's run of fewest steps that reaches it
timed again in turns with Dopri8's (the headline ratio, `head_to_head`: the sweeps are
timed minutes apart, and this machine's load changes), and for
each order the energy-preserving collocation's time against the GONZALEZ-R
composition's; for each energy-exact method, the largest relative energy error and
constraint residual at t = 10 over its runs. Also each scheme's error constant C in
err = C h^p, measured on the quartic's reduced form, for every scheme of
`nhjax.COMPOSITION_SCHEMES`.

Results: benchmarks/results/composition.json.
Run: python benchmarks/composition.py [--repeats 5] [--quick]
"""

import argparse
import itertools
import pathlib
import statistics

import diffrax
import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)

import nhjax as nh  # noqa: E402
from _timing import write  # noqa: E402
from nhjax._reproduce._common import median_time, run_adaptive, run_to  # noqa: E402


T1 = 10.0
TARGETS = (1e-3, 1e-6, 1e-8, 1e-9, 1e-10)
TOLERANCES = tuple(10.0 ** -k for k in np.arange(4, 14.5, 0.5))
# Steps to t = 10 for each order: from where the error is about 1e-2 to below 1e-10.
STEP_COUNTS = {
    2: (50, 100, 200, 400, 800, 1600, 3200, 6400, 12800),
    4: (20, 25, 32, 40, 50, 64, 80, 100, 125, 160, 200, 250, 320, 400, 500, 640),
    6: (16, 20, 25, 32, 40, 50, 64, 80, 100, 125, 160, 200),
    8: (10, 16, 20, 25, 32, 40, 50, 64, 80, 100, 125),
    10: (10, 12, 14, 16, 20, 25, 32, 40, 50, 64),
    12: (8, 10, 12, 14, 16, 20, 25, 32, 40),
}
# The collocation's orders above 2 (`nhjax.EnergyPreservingCollocation.orders`).
COLLOCATION_ORDERS = tuple(order for order in nh.EnergyPreservingCollocation.orders if order > 2)
TSIT5_STEPS = (50, 100, 200, 400, 800, 1600, 3200)
PROJECTED = "Dopri8 + projection (adaptive)"
COLLOCATION = "EP-collocation"
KEPT = " (kept chord matrix)"
# Each timed row keeps its run under this key until the results are written.
FUNCTION = "_function"
HEAD_TO_HEAD_ROUNDS = 7


def _problems():
    quartic = nh.examples.chaotic_quartic(3)
    gearbox = nh.examples.gearbox()
    x0 = quartic.initial_state(0.7)
    return {
        "quartic_n3": dict(system=quartic.canonical, y0=quartic.from_adapted(x0),
                           reduced=(quartic.adapted, x0, quartic.from_adapted)),
        "gearbox": dict(system=gearbox.canonical, y0=gearbox.random_initial_state(jax.random.key(0)), reduced=None),
    }


def _errors(y, reference, invariants) -> dict:
    """The max-norm error of the final (q, p); with `invariants = (canonical system,
    initial energy)`, also its relative energy error and constraint residual."""
    errors = dict(error=max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(y, reference)))
    if invariants is not None:
        canonical, energy = invariants
        errors.update(energy_error=abs(float(canonical.energy(y, None)) / energy - 1),
                      constraint_error=float(jnp.max(jnp.abs(canonical.constraint_residual(y, None)))))
    return errors


def _sweep(system, method, y0, counts, reference, to_canonical, repeats, invariants=None):
    """(steps, h, wall time s, errors) for each step count, one compilation."""
    rows = []
    for n in counts:
        h = jnp.asarray(T1 / n)

        def function(h=h):
            return run_to(system, method, y0, h, jnp.asarray(T1))

        final, succeeded, steps = function()
        if not bool(succeeded) or int(steps) != n:
            rows.append(dict(steps=n, failed=True))
            continue
        seconds = median_time(function, repeats)
        rows.append(dict(steps=n, h=T1 / n, wall_time_s=seconds, failed=False,
                         **_errors(to_canonical(final), reference, invariants), **{FUNCTION: function}))
    return rows


def _identity(y):
    return y


def _dopri8(system, y0, reference, repeats, invariants, solver=diffrax.Dopri8()):
    rows = []
    for tolerance in TOLERANCES:
        def function(tolerance=tolerance):
            return run_adaptive(system, y0, jnp.asarray(T1), jnp.asarray(tolerance), solver)

        final, succeeded, steps = function()
        if not bool(succeeded):
            rows.append(dict(tolerance=tolerance, failed=True))
            continue
        rows.append(dict(tolerance=tolerance, steps=int(steps), wall_time_s=median_time(function, repeats),
                         failed=False, **_errors(final, reference, invariants), **{FUNCTION: function}))
    return rows


def _cheapest(rows, target, by="wall_time_s"):
    """The row reaching `target` with the least `by`: its time in the sweep, or its
    number of steps (`_head_to_head`)."""
    reached = [row for row in rows if not row["failed"] and row["error"] <= target]
    return min(reached, key=lambda row: row[by]) if reached else None


def _error_constant(rows, order):
    """C = err / h^p at the smallest step whose error is above 1e-12 (the asymptotic
    regime, above roundoff)."""
    usable = [row for row in rows if not row["failed"] and row["error"] > 1e-12]
    if not usable:
        return None
    row = min(usable, key=lambda row: row["h"])
    return row["error"] / row["h"] ** order


def work_precision(repeats: int, quick: bool = False) -> dict:
    """Every run above on both problems, the cheapest runs at each target, and the
    schemes' error constants; prints as it goes."""
    thin = (lambda counts: counts[::2]) if quick else (lambda counts: counts)
    results = dict(t1=T1, repeats=repeats, targets=list(TARGETS), problems={})
    for problem_name, problem in _problems().items():
        system, y0 = problem["system"], problem["y0"]
        reference_run = nh.integrate_adaptive(system, y0, T1, rtol=1e-15, atol=1e-15, max_steps=10_000_000)
        reference = jax.tree.map(lambda leaf: leaf[-1], reference_run.ys)
        invariants = (system, float(system.energy(y0, None)))
        runs = {}
        exact = []
        candidates = [("GONZALEZ-R", nh.GonzalezR(), system, y0, _identity)]
        if problem["reduced"] is not None:
            reduced, x0, to_canonical = problem["reduced"]
            candidates.append(("GONZALEZ (reduced form)", nh.DiscreteGradient(), reduced, x0, to_canonical))
        for base_name, base, run_system, start, to_canonical in candidates:
            for order in (2, 4, 6, 8):
                method = base if order == 2 else nh.Composition(base, order)
                name = base_name if order == 2 else f"{base_name}, order {order}"
                runs[name] = _sweep(run_system, method, start, thin(STEP_COUNTS[order]), reference, to_canonical, repeats,
                                    invariants)
                exact.append(name)
                print(f"{problem_name:10s} {name:34s} " + "  ".join(
                    f"N={row['steps']}: {row['error']:.1e} in {row['wall_time_s'] * 1e3:.2f} ms"
                    for row in runs[name] if not row["failed"]), flush=True)
        for order, kept in itertools.product(COLLOCATION_ORDERS, (False, True)):
            name = f"{COLLOCATION}{KEPT if kept else ''}, order {order}"
            runs[name] = _sweep(system, nh.EnergyPreservingCollocation(order, reuse_chord_matrix=kept), y0,
                                thin(STEP_COUNTS[order]), reference, _identity, repeats, invariants)
            exact.append(name)
            print(f"{problem_name:10s} {name:34s} " + "  ".join(
                f"N={row['steps']}: {row['error']:.1e} in {row['wall_time_s'] * 1e3:.2f} ms"
                for row in runs[name] if not row["failed"]), flush=True)
        runs["Tsit5 (fixed steps)"] = _sweep(system, diffrax.Tsit5(), y0, thin(TSIT5_STEPS), reference, _identity, repeats,
                                              invariants)
        runs["Dopri8 (adaptive)"] = _dopri8(system, y0, reference, repeats, invariants)
        runs[PROJECTED] = _dopri8(system, y0, reference, repeats, invariants, nh.Projection(diffrax.Dopri8()))
        exact.append(PROJECTED)
        for name in ("Dopri8 (adaptive)", PROJECTED):
            print(f"{problem_name:10s} {name} " + "  ".join(
                f"tol={row['tolerance']:.0e}: {row['error']:.1e} in {row['wall_time_s'] * 1e3:.2f} ms"
                for row in runs[name] if not row["failed"]), flush=True)
        most_accurate = runs["GONZALEZ-R, order 8"][-1]
        invariant_errors = {
            name: dict(energy=max(row["energy_error"] for row in runs[name] if not row["failed"]),
                       constraint=max(row["constraint_error"] for row in runs[name] if not row["failed"]))
            for name in exact
        }
        for name, worst in invariant_errors.items():
            print(f"{problem_name:10s} {name:34s} largest energy error {worst['energy']:.1e}, "
                  f"constraint {worst['constraint']:.1e}", flush=True)
        results["problems"][problem_name] = dict(
            runs=runs, summary=_summary(problem_name, runs, exact), energy_exact_invariant_errors=invariant_errors,
            reference_check=dict(
                note="distance of the reference (Dopri8 at 1e-15) to GONZALEZ-R order 8 at its smallest step",
                distance=most_accurate.get("error"),
            ),
        )
    results["error_constants_quartic_reduced_form"] = _error_constants(repeats)
    return results


def _summary(problem_name, runs, exact) -> dict:
    """At each target: the cheapest run overall, the cheapest energy-exact run, the
    cheapest symmetric energy-exact run (all but the projection), the cheapest Dopri8
    run, the energy-exact and symmetric runs' times over Dopri8's, and for orders 4, 6
    and 8 the energy-preserving collocation's time over the GONZALEZ-R composition's."""

    def best(names, target):
        found = [(name, _cheapest(runs[name], target)) for name in names]
        found = [(name, row) for name, row in found if row is not None]
        return min(found, key=lambda item: item[1]["wall_time_s"]) if found else (None, None)

    def describe(item):
        return "none" if item[0] is None else f"{item[0]} ({item[1]['wall_time_s'] * 1e3:.2f} ms)"

    summary = {}
    for target in TARGETS:
        overall, energy_exact = best(list(runs), target), best(exact, target)
        dopri8 = best(["Dopri8 (adaptive)"], target)
        ratio = (energy_exact[1]["wall_time_s"] / dopri8[1]["wall_time_s"]
                 if energy_exact[1] is not None and dopri8[1] is not None else None)
        symmetric = best([name for name in exact if name != PROJECTED], target)
        symmetric_ratio = (symmetric[1]["wall_time_s"] / dopri8[1]["wall_time_s"]
                           if symmetric[1] is not None and dopri8[1] is not None else None)
        collocation_over_composition = {}
        for order in (4, 6, 8):
            collocation = _cheapest(runs[f"{COLLOCATION}, order {order}"], target)
            composition = _cheapest(runs[f"GONZALEZ-R, order {order}"], target)
            if collocation is not None and composition is not None:
                collocation_over_composition[order] = collocation["wall_time_s"] / composition["wall_time_s"]
        head_to_head = _head_to_head(runs, [name for name in exact if name != PROJECTED], target)
        summary[f"{target:.0e}"] = dict(
            cheapest=dict(method=overall[0], run=overall[1]),
            cheapest_energy_exact=dict(method=energy_exact[0], run=energy_exact[1]),
            cheapest_symmetric_energy_exact=dict(method=symmetric[0], run=symmetric[1]),
            cheapest_dopri8=dopri8[1],
            energy_exact_over_dopri8=ratio,
            symmetric_energy_exact_over_dopri8=symmetric_ratio,
            collocation_over_gonzalez_r_composition=collocation_over_composition,
            head_to_head=head_to_head,
        )
        print(f"{problem_name:10s} error {target:.0e}: cheapest {describe(overall)}; energy-exact "
              f"{describe(energy_exact)}; symmetric energy-exact {describe(symmetric)}; Dopri8 "
              f"{describe(dopri8)}; ratios " + (f"{ratio:.2f}" if ratio is not None else "n/a") + ", "
              + (f"{symmetric_ratio:.2f}" if symmetric_ratio is not None else "n/a")
              + "; collocation / composition by order "
              + ", ".join(f"{order}: {value:.2f}" for order, value in collocation_over_composition.items())
              + ("" if head_to_head is None else f"; timed in turns: {head_to_head['method']} / Dopri8 "
                                                  f"{head_to_head['ratio']:.2f}"),
              flush=True)
    return summary


def _head_to_head(runs, symmetric_names, target) -> dict | None:
    """The symmetric energy-exact methods against Dopri8 at `target`, timed in turns
    (`HEAD_TO_HEAD_ROUNDS` rounds), so that the ratios do not depend on how this
    machine's load changed between the sweeps: in each round each method is timed
    right after a timing of Dopri8 (`median_time` of 3 calls each), and its ratio is
    the median over the rounds of its time over that Dopri8's, a pair timed within
    milliseconds (a ratio of medians taken across a round of some twenty programs
    moved by 0.2 to 0.4 from run to run on the same code). Each method enters with its run of
    fewest steps that reaches the target, its cheapest by construction (a fixed-step
    run's cost grows with its steps, an adaptive one's with the steps it takes), so
    that a noisy sweep cannot pick a dearer run. Returns the medians and each method's
    ratio, the lowest ratio with its method, and for orders 4, 6 and 8 the cheaper
    collocation's median over the GONZALEZ-R composition's."""

    dopri8 = _cheapest(runs["Dopri8 (adaptive)"], target, by="steps")
    candidates = {name: _cheapest(runs[name], target, by="steps") for name in symmetric_names}
    candidates = {name: row for name, row in candidates.items() if row is not None}
    if dopri8 is None or not candidates:
        return None
    times = {name: [] for name in ["Dopri8 (adaptive)", *candidates]}
    paired = {name: [] for name in candidates}
    for _ in range(HEAD_TO_HEAD_ROUNDS):
        for name, row in candidates.items():
            yardstick = median_time(dopri8[FUNCTION], 3)
            times["Dopri8 (adaptive)"].append(yardstick)
            times[name].append(median_time(row[FUNCTION], 3))
            paired[name].append(times[name][-1] / yardstick)
    medians = {name: statistics.median(values) for name, values in times.items()}
    ratios = {name: statistics.median(values) for name, values in paired.items()}
    best = min(ratios, key=ratios.get)
    collocation_over_composition = {}
    for order in (4, 6, 8):
        collocations = [medians[name] for name in (f"{COLLOCATION}, order {order}", f"{COLLOCATION}{KEPT}, order {order}")
                        if name in medians]
        composition = medians.get(f"GONZALEZ-R, order {order}")
        if collocations and composition is not None:
            collocation_over_composition[order] = min(collocations) / composition
    return dict(rounds=HEAD_TO_HEAD_ROUNDS, dopri8_s=medians["Dopri8 (adaptive)"],
                dopri8_tolerance=dopri8["tolerance"], method=best, steps=candidates[best]["steps"],
                symmetric_s=medians[best], ratio=ratios[best],
                ratios={name: dict(steps=candidates[name]["steps"], seconds=medians[name], ratio=ratio)
                        for name, ratio in ratios.items()},
                collocation_over_gonzalez_r_composition=collocation_over_composition)


def _without_functions(tree):
    """`tree` without the rows' timed functions (`FUNCTION`), for the JSON file."""
    if isinstance(tree, dict):
        return {key: _without_functions(value) for key, value in tree.items() if key != FUNCTION}
    if isinstance(tree, list):
        return [_without_functions(value) for value in tree]
    return tree


def _error_constants(repeats) -> dict:
    """Each scheme's error constant, on the quartic's reduced form (adapted coordinates)."""
    quartic = nh.examples.chaotic_quartic(3)
    x0 = quartic.initial_state(0.7)
    reference = nh.integrate_adaptive(quartic.adapted, x0, T1, rtol=1e-15, atol=1e-15, max_steps=10_000_000)
    reference = (reference.ys[-1],)
    constants = {}
    for scheme, definition in nh.COMPOSITION_SCHEMES.items():
        order = definition["order"]
        method = nh.Composition(nh.DiscreteGradient(), **definition)
        rows = _sweep(quartic.adapted, method, x0, STEP_COUNTS[order][::2], reference, lambda x: (x,), repeats)
        constants[scheme] = dict(order=order, stages=len(definition["coefficients"]),
                                 error_constant=_error_constant(rows, order), runs=rows)
        print(f"scheme {scheme:16s} order {order} stages {constants[scheme]['stages']:2d} "
              f"C = {constants[scheme]['error_constant']:.3g}", flush=True)
    return constants


def markdown(results) -> list[str]:
    """The cheapest runs at each target, as table lines."""
    lines = []
    for problem_name, problem in results["problems"].items():
        lines += [f"## {problem_name}: work against precision to t = {results['t1']:g}", "",
                  "| error | cheapest run | ms | cheapest energy-exact run | ms | cheapest symmetric energy-exact run "
                  "| ms | cheapest Dopri8 ms | energy-exact / Dopri8 | symmetric / Dopri8 | the same, timed in turns |",
                  "|---|---|---:|---|---:|---|---:|---:|---:|---:|---:|"]
        for target, row in problem["summary"].items():
            overall, exact, dopri8 = row["cheapest"], row["cheapest_energy_exact"], row["cheapest_dopri8"]
            symmetric = row["cheapest_symmetric_energy_exact"]
            milliseconds = lambda run: "" if run is None else f"{run['wall_time_s'] * 1e3:.2f}"  # noqa: E731
            ratios = [row["energy_exact_over_dopri8"], row["symmetric_energy_exact_over_dopri8"],
                      (row.get("head_to_head") or {}).get("ratio")]
            lines.append(f"| {target} | {overall['method'] or 'none'} | {milliseconds(overall['run'])} | "
                         f"{exact['method'] or 'none'} | {milliseconds(exact['run'])} | "
                         f"{symmetric['method'] or 'none'} | {milliseconds(symmetric['run'])} | {milliseconds(dopri8)} | "
                         + " | ".join("" if value is None else f"{value:.1f}" for value in ratios) + " |")
        lines.append("")
    return lines


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="every other step count, 3 repeats")
    options = parser.parse_args()
    results = work_precision(3 if options.quick else options.repeats, options.quick)
    results = _without_functions(results)
    write(results, str(pathlib.Path(__file__).parent / "results" / "composition.json"))
    print("\n".join(markdown(results)))


if __name__ == "__main__":
    main()
