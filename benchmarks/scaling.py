"""How the cost of a step grows with the size of the system, every method for
NonholonomicSystems against a dense implicit-midpoint yardstick of the same size, all
timed in one process.

Two families (`--family`), n coordinates each:

- "synthetic" (the default): k = n/4 constraint rows,

      H = |p|^2/2 + |q|^2/2 + sum_i (1 - cos(q_i - q_{i-1})),
      row j of A(q): 1 at 4j, sin(q_{4j+1}) at 4j+2, cos(q_{4j+3})/2 at 4j+3,

  smooth and nonlinear, of full rank everywhere (row j alone has a 1 in column 4j);
  from a fixed state on the constraint.
- "trailers", a real one: a tractor pulling n - 3 trailers down a slope
  (`nhjax.examples.tractor_trailers`), k = n - 2 no-slip rows, a metric that depends on
  q through every trailer's heading, H = p^T M(q)^{-1} p / 2 + V(q) with M written
  out; from the example's usual start (the train on an arc, moving and turning).

Steps of h = 0.05; the number of steps falls with n (`_steps`) so that the slowest runs
stay within minutes. A run that fails (`"successful": false`) stops at its failed step;
its time is recorded but left out of the growth fit and the plot. GONZALEZ-F fails on the
tractor with 61 trailers (n = 64) in its first steps, at h = 0.05 down to 0.0125: its
chord matrix, the Jacobian of the residual with the midpoint gradient in place of the
discrete gradient, contracts the iteration only by about 0.4 per iteration there (the
derivative of the Gonzalez correction, left out of it, is large along the train), and
the iteration ends after its 20 iterations (GONZALEZ-R, which keeps the constraint as
well, takes 4.5). With `root_find_max_steps=40` it completes 40 steps at 10.8
iterations a step; a few steps in, its iterates reach the rounding floor of the
constraint rows (2 to 4 tolerances), which its chord matrix, of condition 740, turns
into corrections of 10 to 20, and the chord iteration recognises that stall in units of
what such a residual moves the iterate by (`nhjax._solver.chord.PresetChord`). The
exact Jacobian at the predictor (with the correction's derivative) takes the first
step in 8 iterations but contracts by only 0.56 at the fifth, where the Jacobian at
the explicit Euler predictor is far from the one at the root; GONZALEZ-F's step ends
alternate (the constraint's residual 1.7e-4 and 1e-6 at every other step for 5
trailers), so a predictor extrapolating the last steps does no better. At h = 0.0125
the iteration stalls at 9 to 45 tolerances in the constraint rows of the train's
tail, with the momentum rows at 0.01: a rounding that the floor (the rounding of the
points evaluated at) does not include, presumably that of the velocity $M(q)^{-1}p$.

For each n and method: median µs/step (`--repeats` timed runs after a warm-up, the
methods and the yardstick of one size timed in turns, `run_and_time_interleaved`, so
that the machine's drift falls on all alike and their ratios hold still),
root-finder iterations per step, seconds to trace, lower and compile (with XLA's default
emitters, and with its loop emitter, `LOOP_EMITTER`), and the process's peak resident
memory after the case's compilation (`ru_maxrss`, a high-water mark: it only grows).
The yardstick solves y' = y + h f((y + y')/2), f = (dH/dp, -dH/dq) of the same H with
the constraint left out, by three Newton iterations a step with a dense Jacobian
(`jax.jacfwd`, `jnp.linalg.solve`). The fitted growth exponent of each method is the
slope of log(µs/step) against log(n) over the sizes from 16 on.

Beside the family, Euler's disk (`nhjax.examples.rolling_disk_3d`, n = 5, k = 2, a
metric that depends on q: a system as a mechanician derives it) in both its forms, the
Hamiltonian from the mass matrix and the Lagrangian (`from_lagrangian`), every method,
h = 0.01 from a generic start, each method's two forms timed in turns, and the
Lagrangian form's time per step over the mass matrix's.

Against SciPy (`--parts scipy`): the same disk to t = 10 as a mechanician who derives it
with sympy would integrate it, SciPy's DOP853 on the equations of
`sympy.physics.mechanics.KanesMethod` (`kane.py`, lambdified to NumPy), against nhjax's
energy-exact runs of its Lagrangian form: the projected Dopri8 over tolerances (one
compiled program, the tolerance traced), GONZALEZ-R and its compositions of order 4
and 6 over step sizes (one compiled program each, `n_steps` traced up to a bound). The
error is the largest difference of positions and velocities at t = 10 from DOP853 at
rtol = atol = 1e-13; times are medians after set-up and compilation, which are reported
apart. For each target error, the cheapest run of each side that reaches it, and their
ratio.

Where GONZALEZ-R's step goes (`--parts profile`), at each n of the family: each piece
of a step timed alone in a compiled loop (`_profile.gonzalez_r_pieces`: the frame, the
products with its derivative, the field, the Gonzalez correction and its derivative in
Taylor form for nearly equal points, a residual, the chord matrix, the residual's
Jacobian that derivatives form, setup and completion), with the size of each piece's
program (`_profile.hlo_counts`: HLO instructions, the operations XLA runs one by
one, about which a small step's cost on XLA:CPU goes, and the distinct fused
computations, one kernel each to compile), and each piece's growth exponent
from n = 16 on; under "gonzalez_r_parts" and the family's name.

Run: python benchmarks/scaling.py [--sizes 4,8,16,32,64] [--repeats R] [--parts family,disk,scipy,profile] [--methods NAME,...]
[--family synthetic|trailers]. Results go to benchmarks/results/scaling.json (the
trailers' under "trailers") and a log-log plot beside it, scaling.png (or
scaling_trailers.png).
"""

import argparse
import json
import pathlib
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)

import nhjax as nh  # noqa: E402
from _profile import gonzalez_r_parts  # noqa: E402
from _timing import CompileTimes, run_and_time, run_and_time_interleaved, timed, write  # noqa: E402
from nhjax._methods import METHODS  # noqa: E402


H = 0.05


def hamiltonian(q, p, args):
    del args
    return 0.5 * p @ p + 0.5 * q @ q + jnp.sum(1 - jnp.cos(q[1:] - q[:-1]))


def constraints(q, args):
    del args
    n = q.shape[0]
    k = n // 4
    rows = jnp.arange(k)
    a = jnp.zeros((k, n), q.dtype)
    a = a.at[rows, 4 * rows].set(1.0)
    a = a.at[rows, 4 * rows + 2].set(jnp.sin(q[4 * rows + 1]))
    return a.at[rows, 4 * rows + 3].set(0.5 * jnp.cos(q[4 * rows + 3]))


SYSTEM = nh.NonholonomicSystem(hamiltonian, constraints)


def initial_state(n):
    q = 0.3 * jnp.sin(jnp.arange(n, dtype=jnp.float64) + 1.0)
    p = jnp.cos(0.7 * jnp.arange(n, dtype=jnp.float64))
    return q, SYSTEM.project_momentum(q, p)


def _steps(n):
    return max(20, 40_000 // n**2)


def _yardstick(hamiltonian, args, y0, steps):
    """Dense implicit midpoint on y' = (dH/dp, -dH/dq), the constraint left out: three
    Newton iterations a step with a `jax.jacfwd` Jacobian."""
    n = y0.shape[0] // 2
    gradient = jax.grad(lambda y: hamiltonian(y[:n], y[n:], args))

    def field(y):
        derivative = gradient(y)
        return jnp.concatenate([derivative[n:], -derivative[:n]])

    def step(y, _):
        def newton(z, _):
            def residual(z):
                return z - y - H * field(0.5 * (y + z))

            return z - jnp.linalg.solve(jax.jacfwd(residual)(z), residual(z)), None

        return jax.lax.scan(newton, y, None, length=3)[0], None

    return jax.lax.scan(step, y0, None, length=steps)[0]


def _synthetic(n):
    """The synthetic family's member of size n: (system, args, start, k)."""
    return SYSTEM, None, initial_state(n), n // 4


def _trailers(n):
    """A tractor pulling n - 3 trailers (`nhjax.examples.tractor_trailers`), from its
    usual start: (system, args, start, k)."""
    example = nh.examples.tractor_trailers(n - 3)
    return example.canonical, example.args, example.initial_state(), n - 2


# Each family: its member of size n, what it is, and its plot's axis.
FAMILIES = {
    "synthetic": (
        _synthetic,
        "synthetic: H = |p|^2/2 + |q|^2/2 + sum(1 - cos(q_i - q_{i-1})), k = n/4 rows",
        "n (coordinates), k = n/4 constraints",
    ),
    "trailers": (
        _trailers,
        "a tractor pulling n - 3 trailers down a slope (nhjax.examples.tractor_trailers), k = n - 2 rows, "
        "a q-dependent metric",
        "n (coordinates) = trailers + 3, k = n - 2 constraints",
    ),
}


def _peak_mib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _in_turns(runs, argument, repeats, steps):
    """Each run's compile figures (`CompileTimes`) and the peak memory after its
    compilation, then µs/step of all the runs timed in turns: ({name: output},
    {name: figures})."""
    figures = {name: dict(**CompileTimes(run, argument).times(), peak_rss_mib=_peak_mib()) for name, run in runs.items()}
    outputs, seconds = run_and_time_interleaved(runs, argument, repeats=repeats)
    for name in runs:
        figures[name]["us_per_step"] = seconds[name] / steps * 1e6
    return outputs, figures


def _method_columns(row, methods) -> str:
    """µs/step and compile seconds of each method in a row, for the log."""
    return "; ".join(
        f"{name} {row[name]['us_per_step']:.1f} ({row[name]['compile_s']:.1f} s, "
        f"{row[name]['loop_emitter_compile_s']:.1f} s with the loop emitter"
        f"{'' if row[name]['successful'] else ', FAILED'})"
        for name in methods
    )


def _methods_in_turns(system, methods, y0, h, steps, repeats, args=None, extra_runs=None):
    """Every method's run of `steps` steps (and `extra_runs`, functions of `y0`), timed
    in turns (`_in_turns`): each one's µs/step, compile s, peak memory, and for the
    methods root-finder iterations per step and whether it succeeded."""
    runs = dict(extra_runs or {})
    for name, method in methods.items():
        runs[name] = _compiled_run(system, method.solver, h, steps, args)
    solutions, figures = _in_turns(runs, y0, repeats, steps)
    _add_outcomes(figures, {name: solutions[name] for name in methods}, steps)
    return figures


def _compiled_run(system, solver, h, steps, args):
    """`steps` steps of `solver` from a state (the argument), saving the end only."""
    return jax.jit(lambda y: nh.integrate(system, solver, y, h, steps, args=args, save_every=steps, throw=False))


def _add_outcomes(figures, solutions, steps):
    """Each run's root-finder iterations per step and whether it succeeded, into its
    figures."""
    for name, solution in solutions.items():
        total = solution.stats.get("root_find_steps")
        figures[name]["iterations_per_step"] = None if total is None else float(total) / steps
        figures[name]["successful"] = bool(solution.result == nh.RESULTS.successful)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="4,8,16,32,64")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--parts", default="family,disk,scipy,profile")
    parser.add_argument("--family", choices=sorted(FAMILIES), default="synthetic")
    parser.add_argument(
        "--methods", default=None,
        help="comma-separated registry names (default: every method for canonical systems); the rows "
        "of the sizes run hold only these, and the sizes not run keep their last rows",
    )
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "scaling.json"))
    options = parser.parse_args()
    sizes = [int(size) for size in options.sizes.split(",")]
    parts = options.parts.split(",")
    methods = {name: method for name, method in METHODS.items() if not method.adapted}
    if options.methods:
        chosen = options.methods.split(",")
        unknown = sorted(set(chosen) - set(methods))
        if unknown:
            parser.error(f"--methods: not methods for canonical systems: {', '.join(unknown)}")
        methods = {name: methods[name] for name in chosen}
    path = pathlib.Path(options.out)
    # Parts not run this time keep their last results.
    results = json.loads(path.read_text()) if path.exists() else {}
    if "scipy" in parts:
        results["rolling_disk_3d_against_scipy"] = _against_scipy(options.repeats)
    if "disk" in parts:
        results["rolling_disk_3d"] = _disk(methods, options.repeats)
    if "profile" in parts:
        _gonzalez_r_profile(options.family, sizes, results, options.out)
    if "family" not in parts:
        write(results, options.out)
        return

    family, description, axis = FAMILIES[options.family]
    stored = results if options.family == "synthetic" else results.get(options.family, {})
    table = {int(n): row for n, row in stored.get("sizes", {}).items() if int(n) not in sizes}
    for n in sizes:
        steps = _steps(n)
        system, args, y0, k = family(n)
        yardstick = jax.jit(lambda y: _yardstick(system.hamiltonian, args, jnp.concatenate(y), steps))
        row = dict(
            k=k,
            steps=steps,
            **_methods_in_turns(system, methods, y0, H, steps, options.repeats, args, dict(yardstick=yardstick)),
        )
        table = dict(sorted({**table, n: row}.items()))
        print(
            f"n = {n:3d}, k = {k:2d}, {steps} steps: yardstick {row['yardstick']['us_per_step']:.1f} µs/step; "
            + _method_columns(row, methods),
            flush=True,
        )
        # Written after each size: the largest sizes take longest, and a run stopped
        # there keeps the others.
        growth = _record(results, options, table, description)

    for name, exponent in growth.items():
        print(f"  {name:<18} grows like n^{exponent:.2f} from n = 16 on")
    plot = pathlib.Path(options.out)
    plot = plot.with_suffix(".png") if options.family == "synthetic" else plot.with_name(
        f"{plot.stem}_{options.family}.png")
    _plot(table, plot, axis)


def _growth_from_16(sizes_and_times) -> float:
    """The slope of log(time) against log(n) over the sizes from n = 16 on."""
    large = [(n, time) for n, time in sizes_and_times if n >= 16]
    return float(np.polyfit(np.log([n for n, _ in large]), np.log([time for _, time in large]), 1)[0])


def _gonzalez_r_profile(family_name, sizes, results, output):
    """GONZALEZ-R's pieces at each size of the family (`_profile.gonzalez_r_parts`),
    with each piece's growth exponent, into `results` and the file `output` (the sizes
    not run keep their last rows)."""
    family = FAMILIES[family_name][0]
    stored = results.get("gonzalez_r_parts", {}).get(family_name, {}).get("sizes", {})
    table = {int(n): row for n, row in stored.items() if int(n) not in sizes}
    for n in sizes:
        system, args, y0, _ = family(n)
        table[n] = gonzalez_r_parts(system, nh.GonzalezR(), y0, H, args)
        print(
            f"GONZALEZ-R's pieces, n = {n}: "
            + "; ".join(f"{name} {part['us']:.1f} µs, {part['operations']} operations" for name, part in table[n].items()),
            flush=True,
        )
        table = dict(sorted(table.items()))
        growth = {}
        if sum(n >= 16 for n in table) >= 2:
            growth = {
                name: _growth_from_16([(n, row[name]["us"]) for n, row in table.items()]) for name in table[max(table)]
            }
        results.setdefault("gonzalez_r_parts", {})[family_name] = dict(
            system=FAMILIES[family_name][1], h=H, sizes=table, growth_exponent_from_16=growth
        )
        # Written after each size, as the family's rows are.
        write(results, output)
    print("  growth from n = 16 on: " + ", ".join(f"{name} n^{value:.2f}" for name, value in growth.items()))


def _completed_sizes(table, name) -> list[int]:
    """The sizes of `table` at which the run `name` was timed and completed its steps (a
    run that failed stopped at its failed step: its time per step means nothing)."""
    return [n for n in sorted(table) if name in table[n] and table[n][name].get("successful", True)]


def _timed_names(table) -> list[str]:
    """The runs timed at some size of `table`, in the order they first appear."""
    names = {}
    for row in table.values():
        names.update((name, None) for name, figures in row.items() if isinstance(figures, dict))
    return list(names)


def _record(results, options, table, description):
    """The family's rows so far, with each run's fitted growth from n = 16 on (over the
    sizes at which it was timed and completed, `_completed_sizes`), into `results` and
    the JSON file (the synthetic family's at the top level, another's under its name);
    returns the growth exponents."""
    growth = {}
    for name in _timed_names(table):
        large = [n for n in _completed_sizes(table, name) if n >= 16]
        if len(large) >= 2:
            growth[name] = _growth_from_16([(n, table[n][name]["us_per_step"]) for n in large])
    figures = dict(system=description, h=H, sizes=table, growth_exponent_from_16=growth)
    if options.family == "synthetic":
        results.update(figures)
    else:
        results[options.family] = figures
    write(results, options.out)
    return growth


DISK_STEPS = 2000


DISK_START = dict(q=jnp.array([0.3, -0.2, 0.4, 0.25, 0.1]), turn_rate=0.6, lean_rate=-0.3, spin_rate=2.5)


def _disk(methods, repeats):
    """Every method on Euler's disk in both forms, the two forms of each method timed in
    turns: µs/step, compile s, iterations, and the Lagrangian form's time over the
    mass matrix's."""
    disk = nh.examples.rolling_disk_3d()
    y0 = disk.state(**DISK_START)
    forms = dict(mass_matrix_hamiltonian=disk.canonical, lagrangian=disk.canonical_from_lagrangian)
    results = {form: {} for form in forms}
    ratios = {}
    for name, method in methods.items():
        for form, figures in _forms_in_turns(forms, method.solver, y0, repeats, disk.args).items():
            results[form][name] = figures
        ratios[name] = results["lagrangian"][name]["us_per_step"] / results["mass_matrix_hamiltonian"][name]["us_per_step"]
    for form in forms:
        print(f"3D rolling disk, {form}: " + _method_columns(results[form], methods), flush=True)
    print("Lagrangian over mass matrix, per step: " + ", ".join(f"{name} {ratio:.2f}" for name, ratio in ratios.items()))
    results["lagrangian_over_mass_matrix"] = ratios
    return results


def _forms_in_turns(forms, solver, y0, repeats, args):
    """One method's runs of `DISK_STEPS` steps on each form, timed in turns (`_in_turns`)."""
    runs = {form: _compiled_run(system, solver, 0.01, DISK_STEPS, args) for form, system in forms.items()}
    solutions, figures = _in_turns(runs, y0, repeats, DISK_STEPS)
    _add_outcomes(figures, solutions, DISK_STEPS)
    return figures


T1 = 10.0
TARGETS = (1e-6, 1e-8, 1e-10)


def _against_scipy(repeats):
    """SciPy's DOP853 on Kane's equations against nhjax's energy-exact runs, Euler's disk
    to t = 10 (see the module docstring)."""
    import diffrax
    import scipy.integrate
    from kane import kanes_equations, PARAMETERS

    disk = nh.examples.rolling_disk_3d()
    system = disk.canonical_from_lagrangian
    q0, p0 = disk.state(**DISK_START)
    velocity = jax.jit(lambda q, p: system.velocity(q, p, disk.args))
    start = time.perf_counter()
    field = kanes_equations()
    sympy_setup_s = time.perf_counter() - start
    parameters = tuple(disk.args[name] for name in PARAMETERS)

    def kane_rhs(_, state):
        qdot, udot = field(state[:5], state[5:], parameters)
        return np.concatenate([qdot, udot])

    initial = np.concatenate([np.asarray(q0), np.asarray(velocity(q0, p0))])

    def dop853(tolerance):
        return scipy.integrate.solve_ivp(kane_rhs, (0.0, T1), initial, method="DOP853", rtol=tolerance, atol=tolerance)

    reference = dop853(1e-13).y[:, -1]

    def error(q, p):
        return float(np.max(np.abs(np.concatenate([np.asarray(q), np.asarray(velocity(q, p))]) - reference)))

    runs = {"SciPy DOP853 (Kane)": []}
    for tolerance in (1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12):
        solution, seconds = run_and_time(dop853, tolerance, repeats=repeats)
        runs["SciPy DOP853 (Kane)"].append(dict(
            setting=tolerance, seconds=seconds,
            error=float(np.max(np.abs(solution.y[:, -1] - reference))), steps=int(solution.t.size - 1),
        ))

    projected = jax.jit(lambda tolerance: nh.integrate_adaptive(
        system, (q0, p0), T1, disk.args, method=nh.Projection(diffrax.Dopri8()), rtol=tolerance, atol=tolerance
    ))
    compile_s = {"Dopri8 + projection": timed(lambda: projected.lower(1e-8).compile())}
    runs["Dopri8 + projection"] = []
    for tolerance in (1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12):
        solution, seconds = run_and_time(projected, tolerance, repeats=repeats)
        runs["Dopri8 + projection"].append(dict(
            setting=tolerance, seconds=seconds,
            error=error(solution.ys[0][-1], solution.ys[1][-1]), steps=int(solution.stats["num_steps"]),
        ))

    fixed = {
        "GONZALEZ-R": (nh.GonzalezR(), (0.05, 0.02, 0.01, 0.005, 0.002)),
        "GONZALEZ-R order 4": (nh.Composition(nh.GonzalezR(), 4), (0.2, 0.1, 0.05, 0.025, 0.0125)),
        "GONZALEZ-R order 6": (nh.Composition(nh.GonzalezR(), 6), (0.25, 0.2, 0.125, 0.1, 0.0625)),
    }
    for name, (method, step_sizes) in fixed.items():
        bound = max(round(T1 / h) for h in step_sizes)
        run = jax.jit(lambda h, n, method=method, bound=bound: nh.integrate(
            system, method, (q0, p0), h, n, args=disk.args, save_every=bound, max_steps=bound, throw=False
        ))
        compile_s[name] = timed(lambda run=run, bound=bound: run.lower(0.1, bound).compile())
        runs[name] = []
        for h in step_sizes:
            n = round(T1 / h)
            solution, seconds = run_and_time(run, h, n, repeats=repeats)
            runs[name].append(dict(
                setting=h, seconds=seconds,
                error=error(solution.ys[0][-1], solution.ys[1][-1]), steps=n,
                successful=bool(solution.result == nh.RESULTS.successful),
            ))

    cheapest = {}
    for target in TARGETS:
        def best(names):
            reached = [(run["seconds"], name, run["setting"]) for name in names for run in runs[name]
                       if run["error"] <= target and run.get("successful", True)]
            return min(reached) if reached else None
        scipy_best, nhjax_best = best(["SciPy DOP853 (Kane)"]), best([name for name in runs if "SciPy" not in name])
        cheapest[str(target)] = dict(
            scipy=scipy_best, nhjax_energy_exact=nhjax_best,
            ratio=None if not (scipy_best and nhjax_best) else nhjax_best[0] / scipy_best[0],
        )
        print(f"error <= {target:g}: SciPy {scipy_best}, nhjax {nhjax_best}, ratio {cheapest[str(target)]['ratio']}")
    print(f"compile s: {compile_s}; sympy set-up {sympy_setup_s:.2f} s", flush=True)
    return dict(t1=T1, form="from_lagrangian", sympy_setup_s=sympy_setup_s, compile_s=compile_s, runs=runs,
                cheapest=cheapest)


def _plot(table, path, axis):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(6, 4.5))
    for name in _timed_names(table):
        sizes = _completed_sizes(table, name)
        axes.loglog(sizes, [table[n][name]["us_per_step"] for n in sizes], "o-", label=name)
    axes.set_xlabel(axis)
    axes.set_ylabel("µs per step")
    axes.set_title("Cost of a step against the size of the system")
    axes.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
