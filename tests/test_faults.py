"""Fault injection: every method, on systems whose functions fail on purpose.

The systems have a clock: a coordinate that no force and no constraint touches, so its
momentum is constant and it advances by the same amount each step. Its value switches
the faults on mid-run: the Hamiltonian (value and gradient) or the constraint matrix
turns NaN, or the constraint matrix vanishes (rank loss), past a threshold set in
`args`; thresholds far away leave the system healthy. The other faults are a
non-finite initial state, a non-finite parameter, `dt = inf` and a step too large for
the root find. One vmapped batch per method holds every fault beside a healthy
trajectory, and each run must
report its exact code, hold non-finite saves from the failure on and finite ones
before, equal its own single run, and have NaN derivatives with respect to the initial
state, the parameters and the step size, forward and reverse, while the healthy one's
are finite.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh

from .helpers import METHODS


N_STEPS = 16
DT = 0.1
FAR = 1e3  # a threshold the clock never reaches
CLOCK_START, CLOCK_SPEED = 0.3, 1.0
# The clock passes this threshold in step 11, from 1.3 to 1.4 (midpoint 1.35).
MID_RUN = CLOCK_START + 10.25 * DT * CLOCK_SPEED


def _beyond(clock, threshold):
    """0 before `threshold`, NaN (value and derivative) from it on. (Not
    `where(clock < threshold, 0, nan * clock)`, whose gradient is NaN everywhere: the
    branch not taken gets a zero cotangent, times its NaN derivative.)"""
    return jnp.where(clock < threshold, 0.0, jnp.nan) * clock


def _canonical_hamiltonian(q, p, args):
    potential = 0.5 * args["stiffness"] * (q[0] ** 2 + q[1] ** 2) + 0.25 * q[0] ** 4 + args["offset"]
    return 0.5 * p @ p + potential + _beyond(q[2], args["nan_hamiltonian_at"])


def _constraints(q, args):
    row = jnp.stack([1.0 + 0.0 * q[0], jnp.sin(q[1]), jnp.zeros_like(q[2])])
    row = row + _beyond(q[2], args["nan_constraints_at"])
    # A row that vanishes from the threshold on: rank 0, not merely small.
    return (row * jnp.where(q[2] < args["rank_lost_at"], 1.0, 0.0))[None, :]


CANONICAL = nh.NonholonomicSystem(_canonical_hamiltonian, _constraints)


def _adapted_hamiltonian(x, args):
    potential = 0.5 * args["stiffness"] * (x[0] ** 2 + x[1] ** 2) + 0.25 * x[0] ** 4 + args["offset"]
    return 0.5 * (x[3] ** 2 + x[4] ** 2) + potential + _beyond(x[2], args["nan_hamiltonian_at"])


def _adapted_structure(x, args):
    """Canonical pairs (x0, x3) and (x2, x4), the clock x2 and its momentum x4, and x1
    coupled to x3 by a skew term."""
    structure = jnp.zeros((5, 5), x.dtype)
    structure = structure.at[0, 3].set(1.0).at[3, 0].set(-1.0)
    structure = structure.at[2, 4].set(1.0).at[4, 2].set(-1.0)
    structure = structure.at[1, 3].set(0.5).at[3, 1].set(-0.5)
    return structure + _beyond(x[2], args["nan_constraints_at"])


ADAPTED = nh.SkewGradientSystem(_adapted_hamiltonian, _adapted_structure)


def _healthy_args():
    return dict(stiffness=1.0, offset=0.0, nan_hamiltonian_at=FAR, nan_constraints_at=FAR, rank_lost_at=FAR)


def _initial_state(system, args, size=1.0, clock=CLOCK_START):
    """The healthy start; `size` scales the motion about the equilibrium (the clock's
    included), `clock` is where the clock starts."""
    if system is ADAPTED:
        return jnp.array([0.4 * size, -0.2 * size, clock, 0.3 * size, CLOCK_SPEED * size])
    q = jnp.array([0.4 * size, -0.2 * size, clock])
    return q, CANONICAL.project_momentum(q, size * jnp.array([0.3, 0.5, CLOCK_SPEED]), args)


# name: (changes to the healthy args, dt, the code)
FAULTS = {
    "healthy": ({}, DT, nh.RESULTS.successful),
    "nan_hamiltonian_mid_run": (dict(nan_hamiltonian_at=MID_RUN), DT, nh.RESULTS.nonfinite_step),
    "nan_constraints_mid_run": (dict(nan_constraints_at=MID_RUN), DT, nh.RESULTS.nonfinite_step),
    "nan_initial_state": ({}, DT, nh.RESULTS.nonfinite_initial_state),
    "nonfinite_parameter": (dict(stiffness=jnp.nan), DT, nh.RESULTS.nonfinite_args),
    "rank_lost_at_start": (dict(rank_lost_at=0.0), DT, nh.RESULTS.constraints_rank_deficient),
    "rank_lost_mid_run": (dict(rank_lost_at=MID_RUN), DT, nh.RESULTS.constraints_rank_deficient),
    "infinite_dt": ({}, jnp.inf, nh.RESULTS.invalid_dt),
    "step_too_large": (dict(stiffness=400.0), 2.0, nh.RESULTS.root_find_not_converged),
    # Not a fault: what must succeed. A motion of size 1e-12 about an equilibrium of
    # energy 1, below the rounding of the energy's values. (Wound angles:
    # tests/test_solver/test_amplitude_and_winding.py, on the gearbox, whose potential
    # is periodic in its angle; here the potential grows with every coordinate.)
    "small_motion": (dict(offset=1.0), DT, nh.RESULTS.successful),
    # The clock a million turns on, its thresholds beyond it: a coordinate held only
    # to 1e-9 beside others of size 1.
    "far_clock": (dict(nan_hamiltonian_at=1e7, nan_constraints_at=1e7, rank_lost_at=1e7), DT, nh.RESULTS.successful),
}
STARTS = {"small_motion": dict(size=1e-12), "far_clock": dict(clock=CLOCK_START + 2e6 * np.pi)}
# A skew-gradient system has no constraint matrix to lose rank.
ADAPTED_FAULTS = [name for name in FAULTS if "rank" not in name]


def _faults_for(system):
    return ADAPTED_FAULTS if system is ADAPTED else list(FAULTS)


def _batch(system, names):
    """The initial states, args and step sizes of the faults `names`, stacked."""
    args, steps = [], []
    for name in names:
        changes, dt, _ = FAULTS[name]
        args.append({key: jnp.asarray(value, dtype=jnp.float64) for key, value in {**_healthy_args(), **changes}.items()})
        steps.append(dt)
    args = jax.tree.map(lambda *leaves: jnp.stack(leaves), *args)
    # Every run starts from the healthy system's state (on its constraint), but those
    # of STARTS and one.
    start = _initial_state(system, _healthy_args())
    nan_start = jax.tree.map(lambda leaf: leaf.at[0].set(jnp.nan), start)
    starts = [
        nan_start
        if name == "nan_initial_state"
        else _initial_state(system, {**_healthy_args(), **FAULTS[name][0]}, **STARTS[name])
        if name in STARTS
        else start
        for name in names
    ]
    states = jax.tree.map(lambda *leaves: jnp.stack(leaves), *starts)
    return states, args, jnp.asarray(steps, dtype=jnp.float64)


def _run(system, method, y0, args, dt, adjoint=None):
    return nh.integrate(system, method, y0, dt, N_STEPS, args=args, throw=False, adjoint=adjoint)


def _system_and_method(name):
    method = METHODS[name]
    return (ADAPTED if isinstance(method, nh.DiscreteGradient) else CANONICAL), method


def _leaves(y):
    return jax.tree.leaves(y)


@pytest.fixture(scope="module", params=list(METHODS))
def batched(request):
    """Each method's vmapped batch of every fault, one compiled program."""
    system, method = _system_and_method(request.param)
    names = _faults_for(system)
    states, args, steps = _batch(system, names)
    run = jax.jit(jax.vmap(lambda y, a, dt: _run(system, method, y, a, dt)))
    return request.param, system, method, names, (states, args, steps), run(states, args, steps)


def test_each_fault_reports_its_code(batched):
    _, _, _, names, _, solution = batched
    for index, name in enumerate(names):
        code = FAULTS[name][2]
        got = jax.tree.map(lambda c: c[index], solution.result)
        assert got == code, f"{name}: expected {nh.RESULTS[code]!r}, got {nh.RESULTS[got]!r}"


def test_saves_are_finite_before_the_failure_and_not_after(batched):
    method_name, _, _, names, _, solution = batched
    for index, name in enumerate(names):
        saved = [leaf[index] for leaf in _leaves(solution.ys)] + [solution.energy[index]]
        finite = np.all(np.stack([np.all(np.isfinite(np.asarray(x).reshape(x.shape[0], -1)), axis=1) for x in saved]), axis=0)
        if FAULTS[name][2] == nh.RESULTS.successful:
            assert finite.all(), name
            continue
        failed_from = np.argmin(finite)
        assert not finite[failed_from:].any(), f"{name}: a finite save after the failure"
        assert finite[:failed_from].all(), f"{name}: a non-finite save before the failure"
        if "mid_run" in name:
            # The clock passes the threshold in step 11; a failed step's save is NaN.
            # GONZALEZ-R with central differences probes A(q) at the midpoint +- h,
            # past the threshold already in step 10 (midpoint 1.25).
            probes_ahead = method_name == "gonzalez-r-central-difference" and name == "nan_constraints_mid_run"
            assert failed_from == (10 if probes_ahead else 11), f"{name}: failed at save {failed_from}"
        elif name != "step_too_large":
            assert failed_from == 0, f"{name}: the initial save should be NaN"


def test_batch_members_equal_their_single_runs(batched):
    _, system, method, names, (states, args, steps), solution = batched
    single = jax.jit(lambda y, a, dt: _run(system, method, y, a, dt))
    for index, name in enumerate(names):
        pick = lambda tree: jax.tree.map(lambda leaf: leaf[index], tree)  # noqa: E731
        alone = single(pick(states), pick(args), steps[index])
        assert alone.result == pick(solution.result), name
        # Equal to rounding: the batched program is vectorised code, compiled apart
        # from the single one, so it may round differently (a few ulps a step, which
        # the large steps of `step_too_large` amplify to 2e-14 in 11 steps).
        for together, apart in zip(_leaves(pick(solution.ys)), _leaves(alone.ys)):
            np.testing.assert_allclose(together, apart, rtol=1e-13, atol=1e-13, err_msg=name)
        if name == "small_motion":
            # Not noise: the motion (from the start, the clock's included) is linear in
            # its size to O(size), so at 1e-12 it is that at 1e-8 scaled, to the
            # rounding of the clock's position relative to it.
            larger = single(_initial_state(system, pick(args), size=1e-8), pick(args), steps[index])
            for small, large in zip(_leaves(alone.ys), _leaves(larger.ys)):
                small, large = (small - small[0]) / 1e-12, (large - large[0]) / 1e-8
                np.testing.assert_allclose(small, large, rtol=0, atol=1e-3 * float(np.max(np.abs(large))))


def _loss(system, method, y0, args, dt, adjoint=None):
    """Reads only the initial save, which is finite for a failure mid-run: its
    derivatives must still be NaN when the run failed."""
    solution = _run(system, method, y0, args, dt, adjoint)
    first = sum(jnp.sum(leaf[0]) for leaf in _leaves(solution.ys))
    return first + solution.energy[0] + solution.ts[0]


@pytest.mark.parametrize("mode", ["reverse", "forward"])
def test_failed_trajectories_have_nan_derivatives(batched, mode):
    """With respect to the initial state, the parameters and dt, forward (jacfwd with
    diffrax.ForwardMode) and reverse (grad): NaN for every failed trajectory, finite for
    the healthy one."""
    _, system, method, names, (states, args, steps), _ = batched
    if mode == "reverse":
        derivative = jax.grad(lambda y, a, dt: _loss(system, method, y, a, dt), argnums=(0, 1, 2))
    else:
        derivative = jax.jacfwd(
            lambda y, a, dt: _loss(system, method, y, a, dt, diffrax.ForwardMode()), argnums=(0, 1, 2)
        )
    gradients = jax.jit(jax.vmap(derivative))(states, args, steps)
    for index, name in enumerate(names):
        y_grad, args_grad, dt_grad = jax.tree.map(lambda leaf: leaf[index], gradients)
        parts = {"y0": _leaves(y_grad), "args": [args_grad["stiffness"]], "dt": [dt_grad]}
        for label, leaves in parts.items():
            values = np.concatenate([np.ravel(leaf) for leaf in leaves])
            if FAULTS[name][2] == nh.RESULTS.successful:
                assert np.all(np.isfinite(values)), f"{name}: d/d{label} not finite"
            else:
                assert np.all(np.isnan(values)), f"{name}: d/d{label} = {values}, not NaN"
