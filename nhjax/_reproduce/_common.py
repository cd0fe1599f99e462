"""What the experiments share: the methods by the paper's names, the chaotic quartic in
its two forms, compiled runs to a final time, fits, thresholds and figure output."""

import dataclasses
import functools
import math
import os
import pathlib
import statistics
import time
from collections.abc import Callable, Sequence
from concurrent.futures import as_completed, ThreadPoolExecutor
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from tqdm.auto import tqdm

import nhjax as nh

from .._methods import Method, METHODS as REGISTRY


# The paper's methods by name (`nhjax._methods.METHODS`), and beyond the paper the
# symmetric compositions (`nhjax.Composition`) of GONZALEZ-R and of GONZALEZ on the
# reduced form, by name, with their orders and colours of their own.
METHODS = {method.name: method for method in REGISTRY.values()}
_COMPOSITION_COLOURS = {"GONZALEZ-R": ("navy", "teal", "purple"), "GONZALEZ": ("C8", "C9", "k")}
COMPOSITIONS = {f"{name} order {order}": order for name in _COMPOSITION_COLOURS for order in (4, 6, 8)}
METHODS.update({
    f"{name} order {order}": Method(
        f"{name} order {order}", functools.partial(nh.Composition, METHODS[name].solver, order), colour
    )
    for name, colours in _COMPOSITION_COLOURS.items()
    for order, colour in zip((4, 6, 8), colours)
})
# The paper's discrete-gradient methods: those whose energy is exact to roundoff.
DISCRETE_GRADIENT_METHODS = tuple(
    method.name for method in REGISTRY.values() if method.keeps_energy and isinstance(method.solver, nh.AbstractMethod)
)
# Every method whose energy is exact to roundoff.
ENERGY_EXACT_METHODS = tuple(name for name, method in METHODS.items() if method.keeps_energy)
EPS = float(np.finfo(np.float64).eps)
# The key of the random initial states (Figures 1, 3 and 4).
SEED = 2016
# Figure 1(d)'s ensemble: the paper's 200 states, at the quick size too. Its slopes are
# statistics of the batch: from 50 states SI-DLA's ranged from 0.27 to 0.76 of the line
# between builds that round differently, across the criterion's edge.
ENSEMBLE_COUNT = 200
# Enough for the runs to t = 10; a constant, so that it never causes a recompilation
# (the runs stop at their own number of steps).
_MAX_STEPS = 1_000_000


def roundoff(n_steps: int) -> float:
    """What "to roundoff" allows after `n_steps` steps: rounding errors of a few eps per
    step that add up as a random walk, with room to spare, $100\\epsilon\\sqrt{N}$."""
    return 100 * EPS * math.sqrt(n_steps)


@dataclasses.dataclass
class Context:
    """One experiment of a reproduction: where its files go, its sizes (the figure's
    own, `_figure.Figure`), whether to show progress, and results computed once and used
    by several experiments (`shared`, kept from one experiment to the next)."""

    out: pathlib.Path
    sizes: Any
    progress: bool
    shared: dict[str, Any] = dataclasses.field(default_factory=dict)

    def chunk_directory(self, name: str) -> pathlib.Path:
        """Where a long run keeps its chunks; the name carries the run's sizes, so that a
        quick and a full reproduction into one folder do not collide."""
        return self.out / "chunks" / name


class Quartic:
    """The chaotic quartic (n = 3) of Figures 1 and 4 in both of its forms: canonical
    states (q, p) for the canonical methods, adapted states (q, rho) for the
    discrete-gradient methods on the reduced equations."""

    def __init__(self):
        self.example = nh.examples.chaotic_quartic(3)

    def system(self, name: str) -> nh.AbstractSystem:
        return self.example.adapted if METHODS[name].adapted else self.example.canonical

    def start(self, name: str, adapted_state):
        """The state `name` integrates from, given the adapted one."""
        return adapted_state if METHODS[name].adapted else self.example.from_adapted(adapted_state)

    def starts(self, name: str, adapted_states):
        """`start` for a batch of states along the leading axis."""
        return jax.vmap(lambda state: self.start(name, state))(adapted_states)

    def canonical(self, name: str, state):
        """(q, p) of a state of `name`'s form (no batch axis)."""
        return self.example.from_adapted(state) if METHODS[name].adapted else state

    def energy(self, y) -> jax.Array:
        return self.example.canonical.energy(y, None)

    def constraint(self, y) -> jax.Array:
        r"""$|\dot x + \sum_i w_i\dot z_i| = |A(q)\,\partial H/\partial p|$ at (q, p)."""
        return jnp.max(jnp.abs(self.example.canonical.constraint_residual(y, None)))

    def reference(self, context: Context, t1: float):
        """(q, p) at `t1` from the sample state by `nhjax.integrate_adaptive` (Dopri8 on
        the index-1 ODE) at rtol = atol = 1e-13: the reference of Figures 1(a) and 4,
        computed once."""
        key = ("quartic reference", t1)
        if key not in context.shared:
            y0 = self.example.from_adapted(self.ensemble()[0])
            solution = nh.integrate_adaptive(self.example.canonical, y0, t1, rtol=1e-13, atol=1e-13)
            context.shared[key] = jax.tree.map(lambda y: y[-1], solution.ys)
        return context.shared[key]

    def ensemble(self):
        """Figure 1(d)'s random adapted states with H = 3.06. The first is the sample
        state: the start of Figure 1(a)-(c) and of Figure 4."""
        return self.example.random_initial_states(jax.random.key(SEED), ENSEMBLE_COUNT)


def state_error(y, reference) -> float:
    """Max-norm distance of two (q, p) states."""
    return max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(y, reference))


@eqx.filter_jit
def run_to(system, method, y0, dt, t1):
    """`method` at the fixed step `dt` from t = 0 to `t1`, a multiple of `dt`: the final
    state, whether every step succeeded, and the number of steps.

    `nhjax.integrate` with `dt` and the number of steps traced up to a constant bound,
    so that one compilation serves every step size, saving only the end. The initial
    constraint is not checked (`check_constraint=False`), so that a GONZALEZ-F state
    whose constraint has drifted may start a run."""
    n_steps = jnp.round(t1 / dt).astype(jnp.int32)
    solution = nh.integrate(
        system, method, y0, dt, n_steps, save_every=_MAX_STEPS, max_steps=_MAX_STEPS, throw=False,
        check_constraint=False,
    )
    final = jax.tree.map(lambda leaf: leaf[-1], solution.ys)
    return final, solution.result == nh.RESULTS.successful, solution.stats["num_steps"]


@eqx.filter_jit
def run_adaptive(system, y0, t1, tolerance, solver=diffrax.Dopri8()):
    """Dopri8 (or `solver`, e.g. `nhjax.Projection(diffrax.Dopri8())`) with a PID
    controller at rtol = atol = `tolerance` on the system's vector field (the index-1
    ODE): the state at `t1`, success, and the number of accepted steps. What
    `nhjax.integrate_adaptive` does, with the tolerance traced so that one compilation
    serves a sweep of tolerances (there they are static)."""
    solution = diffrax.diffeqsolve(
        system,
        solver,
        t0=jnp.zeros_like(t1),
        t1=t1,
        dt0=None,
        y0=y0,
        stepsize_controller=diffrax.PIDController(rtol=tolerance, atol=tolerance),
        max_steps=_MAX_STEPS,
        throw=False,
    )
    final = jax.tree.map(lambda leaf: leaf[-1], solution.ys)
    return final, solution.result == diffrax.RESULTS.successful, solution.stats["num_accepted_steps"]


def usable_cores() -> int:
    """How many cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def concurrently(tasks: Sequence[Callable[[], Any]], description: str, progress: bool) -> list:
    """The results of `tasks`, independent calls without arguments, in their order, run
    in one thread per usable core.

    A figure's runs compile a program each, and XLA compiles (and runs) without holding
    Python's lock: in threads, the programs of independent runs compile on every core
    instead of one after the other. Only the wall time changes: each run is the same
    program on the same inputs, so its numbers are the same. Runs that are timed are
    timed afterwards, one at a time (`median_time`), not here. The first task to fail
    raises its error, and tasks not yet started are dropped."""
    bar = tqdm(total=len(tasks), desc=description, disable=not progress)
    workers = min(len(tasks), usable_cores())
    try:
        if workers <= 1:
            results = []
            for task in tasks:
                results.append(task())
                bar.update()
            return results
        with ThreadPoolExecutor(workers) as pool:
            futures = [pool.submit(task) for task in tasks]
            try:
                for future in as_completed(futures):
                    future.result()
                    bar.update()
            except BaseException:
                pool.shutdown(wait=True, cancel_futures=True)
                raise
        return [future.result() for future in futures]
    finally:
        bar.close()


def check_run(name: str, h: float, t1: float, succeeded, steps) -> None:
    """Raise unless a `run_to` run succeeded in t1 / h steps."""
    if not bool(succeeded):
        raise RuntimeError(f"{name} failed on the way to t = {t1} with h = {h}.")
    if int(steps) != round(t1 / h):
        raise RuntimeError(f"{name} took {int(steps)} steps of h = {h} to t = {t1}, not {round(t1 / h)}.")


def median_time(function, repeats: int, least: float = 0.02) -> float:
    """Median wall time of `function()` over `repeats` timings, JAX's dispatch waited
    for. Each timing calls it often enough to take `least` seconds, as `timeit` does,
    so that sub-millisecond runs are not timer noise. Call it once before (compiling)."""

    def timed(calls):
        start = time.perf_counter()
        for _ in range(calls):
            jax.block_until_ready(function())
        return (time.perf_counter() - start) / calls

    calls = max(1, math.ceil(least / timed(1)))
    return statistics.median(timed(calls) for _ in range(repeats))


def fitted_order(step_sizes, errors) -> float:
    """The slope of log(error) against log(h), least squares."""
    return float(np.polyfit(np.log(step_sizes), np.log(errors), 1)[0])


def _late(times: np.ndarray) -> np.ndarray:
    """The last 90% of `times`: early on a bounded part dominates, later the linear growth."""
    return times >= times[0] + 0.1 * (times[-1] - times[0])


def late_slope(times, values) -> tuple[float, float]:
    """(slope, intercept) of a straight line fitted to `values` over the last 90% of
    `times`."""
    times, values = np.asarray(times), np.asarray(values)
    late = _late(times)
    slope, intercept = np.polyfit(times[late], values[late], 1)
    return float(slope), float(intercept)


def variance_slope_interval(times, deltas, resamples: int = 2000, level: float = 0.95) -> tuple[float, float]:
    r"""A bootstrap interval of `late_slope` of the sample variance over an ensemble:
    `deltas` holds one trajectory per row, `times` its columns. The rows are resampled
    with replacement `resamples` times (with the fixed key `SEED`), the slope of each
    resample's variance is fitted, and the central `level` of those slopes is returned
    (Efron & Tibshirani, *An Introduction to the Bootstrap*, 1993, §13: the percentile
    interval).

    Why: the states of a chaotic ensemble decorrelate within a short time, so two builds
    that round differently sample, in effect, different ensembles, and the slope moves
    by its sampling error from one to the other. The interval is what the ensemble
    determines about the slope; a criterion on the slope alone would test rounding."""
    times, deltas = np.asarray(times), np.asarray(deltas)
    count = deltas.shape[0]
    # A resample as the counts of each row in it: the variances of every resample from
    # two matrix products.
    counts = np.random.default_rng(SEED).multinomial(count, np.full(count, 1 / count), size=resamples)
    means = counts @ deltas / count
    variances = (counts @ deltas**2 - count * means**2) / (count - 1)
    late = _late(times)
    centred = times[late] - times[late].mean()
    slopes = variances[:, late] @ centred / (centred @ centred)
    low, high = np.quantile(slopes, [(1 - level) / 2, (1 + level) / 2])
    return float(low), float(high)


def positive(values, floor: float = 1e-18) -> np.ndarray:
    """`values` with zeros (errors exactly zero) lifted to `floor` for log axes."""
    return np.maximum(np.asarray(values), floor)


def new_figure(columns: int, rows: int = 1) -> tuple[Figure, np.ndarray]:
    """A matplotlib figure on the Agg canvas (no pyplot, no global backend) and its axes."""
    figure = Figure(figsize=(5.2 * columns, 4.0 * rows), layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(rows, columns, squeeze=False)
    return figure, axes


def save_figure(figure: Figure, path: pathlib.Path, legend_size: int = 7) -> str:
    """Every panel gets its legend and a light grid; the PNG's file name is returned."""
    for ax in figure.axes:
        ax.legend(fontsize=legend_size)
        ax.grid(alpha=0.3)
    figure.savefig(path, dpi=120)
    return path.name


def check(passed: bool, text: str, criterion: str, *, secondary: bool = False) -> dict:
    """One claim checked: whether it holds, what was measured (`text`), the quantitative
    `criterion` it was held to, and whether the claim is `secondary`: one the paper
    makes in passing (a failure makes the verdict "partly", not "disagrees")."""
    return dict(passed=bool(passed), text=text, criterion=criterion, secondary=secondary)


def verdict(checks: list[dict]) -> dict:
    """The verdict of an experiment from its checks alone: `status` "agrees" when every
    check holds, "partly" when only secondary ones fail, "disagrees" when any other
    fails; `agrees` (status "agrees"); and `verdict`, one line listing every check with
    its criterion, the failed ones marked NOT."""
    failed = [item for item in checks if not item["passed"]]
    status = "agrees" if not failed else "partly" if all(item["secondary"] for item in failed) else "disagrees"
    parts = [
        f"{'' if item['passed'] else 'NOT '}{item['text']} [criterion: {item['criterion']}]" for item in checks
    ]
    return dict(status=status, agrees=status == "agrees", verdict=f"{status.capitalize()}: " + "; ".join(parts) + ".")
