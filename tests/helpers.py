"""Shared test helpers: order fitting and independent reference solutions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh
from nhjax._methods import METHODS as REGISTRY
from nhjax._reproduce._common import fitted_order as fitted_order


# Every nhjax method, by its name in the package's registry (AVF aside: it differs from
# GONZALEZ only in its discrete gradient, tested in test_discrete_gradient.py), and
# GONZALEZ-R with its finite-difference option and with its chord matrix kept from step
# to step: the shared properties are tested over this one list. GONZALEZ
# (DiscreteGradient) integrates skew-gradient (adapted) systems, the others
# NonholonomicSystems in canonical coordinates.
METHODS = {
    name: method.solver for name, method in REGISTRY.items() if isinstance(method.solver, nh.AbstractMethod)
}
del METHODS["avf"]
METHODS["gonzalez-r-central-difference"] = nh.GonzalezR(derivative="central_difference")
METHODS["gonzalez-r-kept-chord-matrix"] = nh.GonzalezR(reuse_chord_matrix=True)
CANONICAL_METHODS = [name for name in METHODS if name in REGISTRY and not REGISTRY[name].adapted]
KEEPS_ENERGY = {name for name in CANONICAL_METHODS if REGISTRY[name].keeps_energy}
KEEPS_CONSTRAINT = {name for name in CANONICAL_METHODS if REGISTRY[name].keeps_constraint}
# For the few runs long enough that their running time outweighs their compilation
# (tests/conftest.py compiles everything else at XLA's lowest optimisation level).
FULL_OPTIMISATION = {"xla_backend_optimization_level": "2"}


# The examples the shared properties are tested on in canonical coordinates, by the
# catalogue's names (`nhjax.examples.EXAMPLES`), each with a label that says what it
# covers (constant and q-dependent metrics, one and two constraints) and the choices of
# its start (`AbstractExample.start`).
CANONICAL_CASES = {
    "gearbox, M = I": ("gearbox", {}),
    "quartic, n = 7": ("quartic", dict(angle=0.9)),
    "sleigh, q-dependent M": ("sleigh", dict(x1=0.0, rho1=0.3)),
    "disk, k = 2": ("disk", dict(theta=0.2)),
}


def canonical_starts():
    """The examples of `CANONICAL_CASES` with their starts (q, p), by label."""
    starts = {}
    for label, (name, choices) in CANONICAL_CASES.items():
        example = nh.examples.EXAMPLES[name]()
        starts[label] = (example, example.start("canonical", **choices))
    return starts


def equations(jaxpr):
    """Every equation of `jaxpr` and of the jaxprs inside it (loop bodies and
    conditions, branches, calls), depth first."""
    for equation in jaxpr.eqns:
        yield equation
        for value in equation.params.values():
            for inner in value if isinstance(value, (tuple, list)) else [value]:
                inner = getattr(inner, "jaxpr", inner)
                if hasattr(inner, "eqns"):
                    yield from equations(inner)


def relative_energy_error(solution) -> float:
    return float(jnp.max(jnp.abs(solution.energy / solution.energy[0] - 1)))


def reference_final_state(system, y0, t1, args=None):
    """The index-1 ODE (`NonholonomicSystem.vf`, the multiplier eliminated by
    autodiff) by adaptive Dopri8 at rtol = atol = 1e-13 (`nhjax.integrate_adaptive`)."""
    solution = nh.integrate_adaptive(system, y0, t1, args, rtol=1e-13, atol=1e-13)
    return jax.tree.map(lambda y: y[-1], solution.ys)


def first_step(example, method, y0, h):
    """The state after one step of `method` with h from `y0` on `example.canonical`."""
    solution = nh.integrate(example.canonical, method, y0, h, 1, args=example.args)
    return solution.ys[0][1], solution.ys[1][1]


def step_there_and_back(system, method, y0, h, args=None):
    """One step of `method` with h, then one with -h (diffrax's step from t0 = h to
    t1 = 0), returning (the state after both, the diffrax result codes)."""
    state = method.init(system, 0.0, h, y0, args)
    y1, _, _, state, there = method.step(system, 0.0, h, y0, args, state, False)
    back, _, _, _, again = method.step(system, h, 0.0, y1, args, state, False)
    return back, (there, again)


def _max_distance(y, reference) -> float:
    """max |y - reference| over every leaf of two states (arrays or tuples of them)."""
    return float(max(jax.tree.leaves(jax.tree.map(lambda a, b: jnp.max(jnp.abs(a - b)), y, reference))))


def final_states(system, method, y0, t1, step_sizes, args=None):
    """The state at t1 for each step size, from one compiled program: the number of
    steps is traced up to the most any size needs (`max_steps`), as is dt."""
    steps = [round(t1 / h) for h in step_sizes]
    bound = max(steps)
    finals = []
    for h, n in zip(step_sizes, steps):
        solution = nh.integrate(system, method, y0, h, n, args=args, save_every=bound, max_steps=bound, throw=False)
        assert solution.result == nh.RESULTS.successful, f"failed before t1 at h = {h}: {nh.RESULTS[solution.result]}"
        finals.append(jax.tree.map(lambda y: y[-1], solution.ys))
    return finals


def final_state_errors(system, method, y0, t1, step_sizes, reference, args=None, observe=None):
    """max |observe(y(t1)) - reference| for each step size (`final_states`); states may
    be tuples such as (q, p)."""
    observe = (lambda y: y) if observe is None else observe
    return [_max_distance(observe(final), reference) for final in final_states(system, method, y0, t1, step_sizes, args)]


def runs_at_step_sizes(system, method, y0, step_sizes, n_steps, args=None, compiler_options=None):
    """`n_steps` steps of `method` from `y0` at each of `step_sizes`, one vmapped run
    (`throw=False`), every step saved; compiled with XLA's `compiler_options` where
    given (`FULL_OPTIMISATION` for long runs)."""

    def run(dt):
        return nh.integrate(system, method, y0, dt, n_steps, args=args, throw=False)

    dts = jnp.array(step_sizes)
    if compiler_options is None:
        return jax.vmap(run)(dts)
    return jax.jit(jax.vmap(run)).lower(dts).compile(compiler_options=compiler_options)(dts)


def errors_at(runs, step_sizes, t1, reference, observe=None):
    """For `runs_at_step_sizes` output: max |observe(y(t1)) - reference| at each step
    size; states may be tuples such as (q, p)."""
    observe = (lambda y: y) if observe is None else observe
    return [
        _max_distance(observe(jax.tree.map(lambda y: y[index, round(t1 / h)], runs.ys)), reference)
        for index, h in enumerate(step_sizes)
    ]


def energy_variance_slopes(system, method, states, sizes=(0.2, 0.1), n_steps=20_000):
    """For each step size h, the slope in t of the sample variance over `states` of
    H(t) - H(0), to t = n_steps h, fitted with an intercept over the last 90%; all runs
    in one compiled batch."""
    sizes = jnp.repeat(jnp.array(sizes), states[0].shape[0])
    batch = jax.tree.map(lambda y: jnp.concatenate([y, y]), states)

    def run(y, h):
        return nh.integrate(system, method, y, h, n_steps, save_every=n_steps // 40)

    # Long runs: compiled at XLA's full optimisation, whatever the suite's level.
    compiled = jax.jit(jax.vmap(run)).lower(batch, sizes).compile(compiler_options=FULL_OPTIMISATION)
    solution = compiled(batch, sizes)
    assert bool(jnp.all(solution.result == nh.RESULTS.successful))
    slopes = []
    for h, energy, times in zip(*(jnp.split(x, 2) for x in (sizes, solution.energy, solution.ts))):
        variance = np.var(np.asarray(energy - energy[:, :1]), axis=0, ddof=1)
        times = np.asarray(times[0])
        late = times >= times[-1] / 10
        slopes.append((float(h[0]), float(np.polyfit(times[late], variance[late], 1)[0])))
    return slopes


def check_per_trajectory_result_codes(method):
    """Under jit and vmap, a batch of three: a NaN start, a trajectory that runs into a
    singular potential mid-run, and a good one. Each gets its own code; the good one
    equals its single run."""

    def hamiltonian(q, p, args):
        # sqrt(1 - q3) pulls q3 towards 1, past which it is NaN.
        return 0.5 * (p @ p + q[0] ** 2 + q[1] ** 2) + jnp.sqrt(1.0 - q[2])

    def constraints(q, args):
        return jnp.array([[1.0, jnp.sin(q[2]), 0.0]])

    system = nh.NonholonomicSystem(hamiltonian, constraints)

    def start(q3, p3):
        q = jnp.array([0.1, 0.2, q3])
        return q, system.project_momentum(q, jnp.array([0.5, -0.5, p3]))

    def run(y0):
        return nh.integrate(system, method, y0, 0.1, 40, throw=False)

    good = start(-3.0, -0.5)
    singular = start(0.5, 1.0)
    nan = jax.tree.map(lambda y: y.at[0].set(jnp.nan), good)
    batch = jax.jit(jax.vmap(run))(jax.tree.map(lambda *y: jnp.stack(y), nan, singular, good))
    assert bool((batch.result == nh.RESULTS.nonfinite_initial_state)[0])
    # NaN forces: the system's functions fail, and the code says so (not the root find
    # that they make fail).
    assert bool((batch.result == nh.RESULTS.nonfinite_step)[1])
    assert bool((batch.result == nh.RESULTS.successful)[2])
    assert not bool(jnp.any(jnp.isfinite(batch.ys[0][0, 1:])))
    finite = jnp.all(jnp.isfinite(batch.ys[0][1]), axis=1)
    assert bool(finite[1]) and not bool(finite[-1])  # it fails after a few steps, and stays failed
    # The batch is vectorised code compiled apart from the single run, so its rounding
    # differs, and each root agrees to the root finder's tolerance (64 eps), not bitwise.
    single = run(good)
    np.testing.assert_allclose(batch.ys[0][2], single.ys[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(batch.ys[1][2], single.ys[1], rtol=0, atol=1e-12)
    with pytest.raises(RuntimeError, match="failed at step .*non-finite state"):
        nh.integrate(system, method, singular, 0.1, 40)


def check_float32(method, example, y0):
    """1000 steps in float32 on `example`: float32 states, the constraint within 100
    eps, the energy within the method's own error."""
    y0 = jax.tree.map(lambda y: y.astype(jnp.float32), y0)
    solution = nh.integrate(example.canonical, method, y0, 0.1, 1000, args=example.args, save_every=10)
    assert solution.result == nh.RESULTS.successful
    assert solution.ys[0].dtype == jnp.float32
    eps = float(jnp.finfo(jnp.float32).eps)
    assert float(jnp.max(jnp.abs(solution.constraint))) <= 100 * eps
    assert relative_energy_error(solution) < 1e-2
