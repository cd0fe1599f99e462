"""Every method on systems with a force and a dissipation: the discrete power balance of
the discrete-gradient methods to roundoff, orders against independent references, the
ledger (`Solution.work`, `Solution.dissipated`) against an independent quadrature,
derivatives with respect to the torques, and per-trajectory failures."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh

from .helpers import fitted_order, KEEPS_CONSTRAINT, METHODS


DISK = nh.examples.rolling_disk()
ROBOT = nh.examples.differential_drive(torques=((0.05, 0.08),))
REFERENCE = dict(rtol=1e-13, atol=1e-13)


def _damping(q, p, args):
    """State-dependent damping of the heading and the rolling angle."""
    return jnp.diag(jnp.array([0.0, 0.0, 0.3, 0.2], q.dtype)) * (1 + q[2] ** 2)


def _torques(t, q, p, args):
    """A steering torque varying in time and a drive on the wheel that follows the
    state."""
    return jnp.stack([0.0 * t, 0.0 * t, jnp.sin(t), 0.5 * jnp.cos(q[2])])


FORCED_DISK = nh.NonholonomicSystem(DISK.canonical.hamiltonian, DISK.canonical.constraints, _damping, _torques)
DAMPED_DISK = nh.NonholonomicSystem(DISK.canonical.hamiltonian, DISK.canonical.constraints, _damping)


# The same disk in adapted coordinates x = (q, rho), for `nhjax.DiscreteGradient`: with the
# frame X = (X_1, X_2), X_1 rolling (phi), X_2 turning (theta), R = diag(0, X^T D X) and
# g = (0, X^T F) by hand.
def _adapted_damping(x, args):
    return jnp.diag(jnp.array([0.0, 0.0, 0.0, 0.0, 0.2, 0.3], x.dtype)) * (1 + x[2] ** 2)


def _adapted_torques(t, x, args):
    return jnp.zeros_like(x).at[4].set(0.5 * jnp.cos(x[2])).at[5].set(jnp.sin(t))


FORCED_DISK_ADAPTED = nh.SkewGradientSystem(
    DISK.adapted.hamiltonian, DISK.adapted.structure, _adapted_damping, _adapted_torques
)
DAMPED_DISK_ADAPTED = nh.SkewGradientSystem(DISK.adapted.hamiltonian, DISK.adapted.structure, _adapted_damping)


def test_the_adapted_disk_is_the_canonical_one():
    """The forced disk's two forms: the same energy and the same power, supplied and
    dissipated, at states and times that correspond."""
    for theta, t in ((0.2, 0.0), (1.1, 2.5)):
        y, x = DISK.start("canonical", theta=theta), DISK.start("adapted", theta=theta)
        np.testing.assert_allclose(FORCED_DISK.energy(y, DISK.args), FORCED_DISK_ADAPTED.energy(x, DISK.args), rtol=1e-15)
        np.testing.assert_allclose(
            FORCED_DISK.power(t, y, DISK.args), FORCED_DISK_ADAPTED.power(t, x, DISK.args), rtol=1e-14, atol=1e-15
        )


def _takes_adapted(method) -> bool:
    return getattr(method, "term_structure", None) is nh.SkewGradientSystem


def _disk_run(method, forced, dt, n_steps, **kwargs):
    """`nhjax.integrate` of the forced (or only damped) disk from theta = 0.2, in the form
    the method takes."""
    if _takes_adapted(method):
        system, start = (FORCED_DISK_ADAPTED if forced else DAMPED_DISK_ADAPTED), DISK.start("adapted", theta=0.2)
    else:
        system, start = (FORCED_DISK if forced else DAMPED_DISK), DISK.start("canonical", theta=0.2)
    return nh.integrate(system, method, start, dt, n_steps, DISK.args, **kwargs)


BALANCED = {
    "gonzalez-r": nh.GonzalezR(),
    "gonzalez-f": nh.GonzalezF(),
    "gonzalez": METHODS["gonzalez"],
    "gonzalez-r, order-4 composition": nh.Composition(nh.GonzalezR(), 4),
    "dopri8-projection": nh.Projection(diffrax.Dopri8()),
}


@pytest.mark.parametrize("name", BALANCED)
def test_the_discrete_power_balance_holds_to_roundoff(name):
    """Over 10^4 steps with a time-varying force and a state-dependent damping,
    H(y_k) - H(y_0) = W_k - D_k to roundoff at every save, as the discrete gradient
    (or the projection onto the balance) makes it; with the damping alone the energy
    never increases from one step to the next."""
    solution = _disk_run(BALANCED[name], True, 0.01, 10_000, save_every=100)
    scale = 1 + float(jnp.max(jnp.abs(solution.energy)))
    balance = solution.energy - solution.energy[0] - (solution.work - solution.dissipated)
    assert float(jnp.max(jnp.abs(balance))) / scale < 1e-12, float(jnp.max(jnp.abs(balance)))
    assert float(solution.work[-1]) > 1 and float(solution.dissipated[-1]) > 1  # both matter
    assert bool(jnp.all(jnp.diff(solution.dissipated) >= 0))
    damped = _disk_run(BALANCED[name], False, 0.01, 1000)
    rises = jnp.diff(damped.energy)
    eps = float(jnp.finfo(rises.dtype).eps)
    assert float(jnp.max(rises)) <= 8 * eps * float(damped.energy[0])
    assert float(damped.energy[-1]) < 0.5 * float(damped.energy[0])


ORDER_CASES = {
    "differential drive": (ROBOT.canonical, ROBOT.start("canonical"), ROBOT.args, 2.0, (0.2, 0.1, 0.05)),
    "disk, sin t and damping": (FORCED_DISK, DISK.start("canonical", theta=0.2), DISK.args, 1.0, (0.1, 0.05, 0.025)),
    "disk, sin t and damping, adapted": (
        FORCED_DISK_ADAPTED, DISK.start("adapted", theta=0.2), DISK.args, 1.0, (0.1, 0.05, 0.025)
    ),
}


def _fitted_orders(method, case):
    """The fitted orders of the state at t1 and of the ledger's work and dissipated
    energy against the Dopri8 reference, which integrates v^T F and v^T D v along the
    index-1 flow; and the largest constraint residual of the runs."""
    system, y0, args, t1, sizes = ORDER_CASES[case]
    reference = nh.integrate_adaptive(system, y0, t1, args, **REFERENCE)
    final = jax.tree.leaves(jax.tree.map(lambda y: y[-1], reference.ys))
    work, dissipated = float(reference.work[-1]), float(reference.dissipated[-1])
    errors, ledger_errors, constraint = [], [], 0.0
    bound = round(t1 / min(sizes))  # one compiled program for every step size
    for h in sizes:
        solution = nh.integrate(system, method, y0, h, round(t1 / h), args, save_every=bound, max_steps=bound)
        state = jax.tree.leaves(jax.tree.map(lambda y: y[-1], solution.ys))
        errors.append(max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(state, final)))
        ledger_errors.append(
            max(abs(float(solution.work[-1]) - work), abs(float(solution.dissipated[-1]) - dissipated))
        )
        if solution.constraint is not None:
            constraint = max(constraint, float(jnp.max(jnp.abs(solution.constraint))))
    return fitted_order(sizes, errors), fitted_order(sizes, ledger_errors), constraint


@pytest.mark.parametrize("name", list(METHODS))
def test_every_method_keeps_its_order_with_forces(name):
    """On the differential-drive robot (torques, bearing friction), and for the methods
    of skew-gradient systems on the forced disk in adapted coordinates: the method's
    order (2, or 4 and 6 for the energy-preserving collocations) in the state and in
    the ledger against the reference, and the constraint to roundoff for the methods
    that keep it."""
    method = METHODS[name]
    order = method.order(None)
    case = "disk, sin t and damping, adapted" if _takes_adapted(method) else "differential drive"
    state_order, ledger_order, constraint = _fitted_orders(method, case)
    assert order - 0.3 <= state_order <= order + 0.6, state_order
    assert order - 0.3 <= ledger_order <= order + 0.6, ledger_order
    if name in KEEPS_CONSTRAINT or name == "gonzalez-r-central-difference":
        assert constraint < 1e-13, constraint


@pytest.mark.parametrize("name, order", [("gonzalez-r", 2), ("gonzalez-r, order-4 composition", 4), ("spark", 2)])
def test_orders_with_a_time_dependent_force(name, order):
    """On the disk with a force varying in time and a state-dependent damping: the
    order of GONZALEZ-R and SPARK (whose stages see their own times), and 4 for the
    composition, whose substeps must see theirs."""
    method = BALANCED.get(name) or METHODS[name]
    state_order, ledger_order, _ = _fitted_orders(method, "disk, sin t and damping")
    assert order - 0.3 <= state_order <= order + 0.6, state_order
    assert order - 0.3 <= ledger_order <= order + 0.6, ledger_order


def test_the_robot_drives_straight_and_turns_as_the_closed_forms_say():
    """Equal torques: x(t) of the closed form, no turn; opposite torques: theta(t) of the
    closed form, no drift; GONZALEZ-R at h = 0.05, error O(h^2)."""
    straight = nh.examples.differential_drive(torques=((0.05, 0.05),))
    turn = nh.examples.differential_drive(torques=((-0.05, 0.05),))
    y0 = straight.start("canonical")
    run = jax.jit(lambda args: nh.integrate(straight.canonical, nh.GonzalezR(), y0, 0.05, 80, args, save_every=80))
    ahead, turned = run(straight.args), run(turn.args)
    x, _ = straight.straight_run(0.05, 4.0)
    theta, _ = turn.turn_in_place(0.05, 4.0)
    assert abs(float(ahead.ys[0][-1, 0]) - float(x)) < 1e-5 and abs(float(ahead.ys[0][-1, 2])) < 1e-14
    assert abs(float(turned.ys[0][-1, 2]) - float(theta)) < 1e-4
    assert float(jnp.max(jnp.abs(turned.ys[0][-1, :2]))) < 1e-14


def test_no_force_and_no_damping_run_as_the_conservative_system():
    """A force and a dissipation that are zero: every method's states equal the
    conservative run's (they add exact zeros), and the ledger stays zero."""
    zero = nh.NonholonomicSystem(
        DISK.canonical.hamiltonian,
        DISK.canonical.constraints,
        lambda q, p, args: jnp.zeros((4, 4), q.dtype),
        lambda t, q, p, args: jnp.zeros_like(q),
    )
    y0 = DISK.start("canonical", theta=0.2)
    for name in ("gonzalez-r", "sidla", "spark"):
        forced = nh.integrate(zero, METHODS[name], y0, 0.1, 20, DISK.args)
        free = nh.integrate(DISK.canonical, METHODS[name], y0, 0.1, 20, DISK.args)
        np.testing.assert_allclose(forced.ys[1], free.ys[1], rtol=0, atol=1e-14, err_msg=name)
        assert float(jnp.max(jnp.abs(forced.work))) == 0 and float(jnp.max(jnp.abs(forced.dissipated))) == 0


def _robot_outcome(torques):
    """The final pose and energy exchange of the robot under piecewise-constant
    torques (4 pieces over T = 2, steps of 0.05 that divide them), in one number."""
    robot = nh.examples.differential_drive(torques=torques, duration=2.0)
    solution = nh.integrate(
        robot.canonical, nh.GonzalezR(), robot.start("canonical"), 0.05, 40, robot.args, save_every=40, throw=False
    )
    q = solution.ys[0][-1]
    return q[0] + 2 * q[1] + q[2] + solution.work[-1] - solution.dissipated[-1]


def test_derivatives_with_respect_to_the_torques_match_finite_differences():
    """d(final pose, work, dissipated)/d(torques) by reverse and forward mode through
    GONZALEZ-R (replayed from the stored roots), against central differences."""
    torques = jnp.array([[0.05, 0.08], [0.1, -0.02], [0.0, 0.06], [-0.04, 0.03]])
    reverse = jax.grad(_robot_outcome)(torques)
    forward = jax.jacfwd(_robot_outcome)(torques)
    step = 1e-6
    differences = np.zeros(torques.shape)
    for index in np.ndindex(*torques.shape):
        up = float(_robot_outcome(torques.at[index].add(step)))
        down = float(_robot_outcome(torques.at[index].add(-step)))
        differences[index] = (up - down) / (2 * step)
    np.testing.assert_allclose(reverse, differences, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(forward, reverse, rtol=1e-10, atol=1e-12)


def test_a_failing_trajectory_keeps_its_code_and_spoils_no_other():
    """Under vmap: a torque that turns NaN mid-run is a non-finite step, a negative
    friction an indefinite dissipation at the start; the good trajectory equals its
    single run, the failed ones have NaN derivatives, the good one's are finite."""
    robot = nh.examples.differential_drive(duration=2.0)
    y0 = robot.start("canonical")
    canonical = robot.canonical

    def failing_force(t, q, p, args):
        return jnp.where(t > args["fails_after"], jnp.nan, 1.0) * canonical.force(t, q, p, args)

    system = nh.NonholonomicSystem(canonical.hamiltonian, canonical.constraints, canonical.dissipation, failing_force)

    def run(torque, friction, fails_after):
        args = {**robot.args, "torques": jnp.stack([torque, 0.08])[None], "friction": friction, "fails_after": fails_after}
        return nh.integrate(system, nh.GonzalezR(), y0, 0.05, 40, args, save_every=10, throw=False)

    torques, frictions = jnp.array([0.05, 0.05, 0.05]), jnp.array([0.02, 0.02, -0.02])
    fails_after = jnp.array([10.0, 1.0, 10.0])
    batch = jax.vmap(run)(torques, frictions, fails_after)
    assert list(batch.result == nh.RESULTS.successful) == [True, False, False]
    assert bool((batch.result == nh.RESULTS.nonfinite_step)[1])
    assert bool((batch.result == nh.RESULTS.dissipation_not_positive_semidefinite)[2])
    assert bool(jnp.all(jnp.isfinite(batch.work[1, :2]))) and not bool(jnp.any(jnp.isfinite(batch.work[1, 3:])))
    single = run(0.05, 0.02, 10.0)
    np.testing.assert_allclose(batch.ys[0][0], single.ys[0], rtol=0, atol=1e-13)
    np.testing.assert_allclose(batch.work[0], single.work, rtol=0, atol=1e-13)
    derivatives = jax.vmap(jax.grad(lambda *inputs: run(*inputs).ys[0][-1, 0]))(torques, frictions, fails_after)
    assert bool(jnp.isfinite(derivatives[0])) and abs(float(derivatives[0])) > 0
    assert bool(jnp.all(jnp.isnan(derivatives[1:])))


def test_a_chunked_forced_run_sums_its_ledger_across_the_chunks(tmp_path):
    """`nhjax.run_chunked` restarts the ledger at each chunk and sums it when joining:
    the same work and dissipated energy as one run, to roundoff."""
    y0 = DISK.start("canonical", theta=0.2)
    whole = nh.integrate(FORCED_DISK, nh.GonzalezR(), y0, 0.05, 60, DISK.args, save_every=10)
    chunked = nh.run_chunked(
        FORCED_DISK, nh.GonzalezR(), y0, 0.05, 60, directory=tmp_path, args=DISK.args, save_every=10,
        chunk_steps=20, progress=False,
    )
    np.testing.assert_allclose(chunked.work, whole.work, rtol=0, atol=1e-12)
    np.testing.assert_allclose(chunked.dissipated, whole.dissipated, rtol=0, atol=1e-12)
    balance = chunked.energy - chunked.energy[0] - (chunked.work - chunked.dissipated)
    assert float(jnp.max(jnp.abs(balance))) < 1e-12


def test_the_rolling_resistance_and_the_blade_friction_in_every_form():
    """The disk with rolling resistance and the sleigh with friction along the blade:
    the canonical, Lagrangian and adapted forms give one motion (the adapted mapped
    back), the disk's also that of its closed form; the disk's rolling and the sleigh's
    speed decay; GONZALEZ-R converges to the disk's closed form at order 2."""
    disk = nh.examples.rolling_disk(rolling_resistance=0.3)
    sleigh = nh.examples.chaplygin_sleigh(blade_friction=0.5)
    assert not nh.examples.rolling_disk().canonical.is_forced()
    for example, choices in ((disk, dict(theta=0.2)), (sleigh, dict(x1=0.0, rho1=0.3))):
        t1 = 3.0
        runs = {
            form: nh.integrate_adaptive(example.system(form), example.start(form, **choices), t1, example.args, **REFERENCE)
            for form in ("canonical", "lagrangian", "adapted")
        }
        adapted_end = example.from_adapted(runs["adapted"].ys[-1])
        for form in ("canonical", "lagrangian"):
            np.testing.assert_allclose(runs[form].ys[0][-1], adapted_end[0], rtol=0, atol=1e-10, err_msg=form)
            np.testing.assert_allclose(runs[form].ys[1][-1], adapted_end[1], rtol=0, atol=1e-10, err_msg=form)
            np.testing.assert_allclose(runs[form].dissipated, runs["adapted"].dissipated, rtol=0, atol=1e-10)
        assert float(runs["adapted"].energy[-1]) < 0.9 * float(runs["adapted"].energy[0])
    x0 = disk.initial_state(theta=0.2)
    np.testing.assert_allclose(
        nh.integrate_adaptive(disk.adapted, x0, 3.0, disk.args, **REFERENCE).ys[-1], disk.exact_solution(3.0, x0),
        rtol=0, atol=1e-11,
    )
    sizes = (0.2, 0.1, 0.05)
    errors = []
    bound = round(2.0 / min(sizes))
    for h in sizes:
        run = nh.integrate(
            disk.canonical, nh.GonzalezR(), disk.start("canonical", theta=0.2), h, round(2.0 / h), disk.args,
            save_every=bound, max_steps=bound,
        )
        errors.append(float(jnp.max(jnp.abs(run.ys[0][-1] - disk.exact_solution(2.0, x0)[:4]))))
    assert 1.8 <= fitted_order(sizes, errors) <= 2.3
