"""Derivatives through whole trajectories of every method: reverse mode against central
finite differences, forward mode against reverse mode, the exact identity
dH(y_N)/dtheta = dH(y_0)/dtheta of the energy-preserving methods, derivatives with
respect to system parameters, NaN derivatives through failed runs, and the default
route of derivatives (the run replayed from its stored roots, `nhjax._replay`) against
diffrax's checkpointed loop.

Each case is a map theta -> (initial state, args) on the constraint, with theta holding
the initial positions, an unprojected momentum and the system's parameters, and the
outputs F(theta) = (a fixed linear functional of y_N, H(y_N), H(y_0)). One jitted,
vmapped program per case returns F and its reverse-mode Jacobian at theta and at the
2 d finite-difference points, so the finite differences cost no extra compilation."""

import diffrax
import jax
import jax.numpy as jnp
import pytest

import nhjax as nh
from nhjax._methods import METHODS as REGISTRY


N_STEPS = 200
SLEIGH = nh.examples.chaplygin_sleigh()
SLEIGH_PARAMETERS = ("J", "a", "m")


def _gearbox_with_parameters():
    """The gearbox of §4.4 with a spring stiffness in H and a gear ratio in A, so that
    derivatives with respect to `args` pass through both."""

    def hamiltonian(q, p, args):
        springs = 0.5 * args["stiffness"] * (q[0] ** 2 + q[1] ** 2)
        return 0.5 * p @ p + springs + jnp.cos(q[2]) - 0.2 * jnp.sin(2 * q[2])

    def constraints(q, args):
        return jnp.stack([jnp.ones_like(q[2]), args["gear"] * jnp.sin(q[2]), jnp.zeros_like(q[2])])[None]

    return nh.NonholonomicSystem(hamiltonian, constraints)


GEARBOX = _gearbox_with_parameters()


def _canonical_case(system, names, q0, momentum, parameters, dt):
    """theta = (q0, unprojected p0, parameters) for a `NonholonomicSystem`."""
    n = q0.shape[0]

    def build(theta):
        args = {name: theta[2 * n + i] for i, name in enumerate(names)}
        q = theta[:n]
        return (q, system.project_momentum(q, theta[n : 2 * n], args)), args

    theta = jnp.concatenate([q0, momentum, jnp.asarray(parameters)])
    return system, build, theta, dt


def _gearbox_case():
    return _canonical_case(
        GEARBOX,
        ("stiffness", "gear"),
        jnp.array([0.6, -0.4, 0.3]),
        jnp.array([-0.3, 0.8, 0.5]),
        (1.3, 0.8),
        0.05,
    )


def _sleigh_case():
    q0 = jnp.array([0.2, -0.1, 0.3])
    p0 = SLEIGH.from_adapted(jnp.array([0.2, -0.1, 0.3, 0.5, -0.6]), SLEIGH.args)[1]
    return _canonical_case(
        SLEIGH.canonical, SLEIGH_PARAMETERS, q0, p0, [SLEIGH.args[k] for k in SLEIGH_PARAMETERS], 0.1
    )


def _adapted_sleigh_case():
    """The discrete-gradient method on the sleigh's reduced equations: theta = (x0,
    parameters)."""

    def build(theta):
        return theta[:5], {name: theta[5 + i] for i, name in enumerate(SLEIGH_PARAMETERS)}

    x0 = jnp.array([0.2, -0.1, 0.3, 0.5, -0.6])
    theta = jnp.concatenate([x0, jnp.array([SLEIGH.args[k] for k in SLEIGH_PARAMETERS])])
    return SLEIGH.adapted, build, theta, 0.1


CASES = {
    "gearbox": _gearbox_case,
    "sleigh": _sleigh_case,
    "adapted sleigh": _adapted_sleigh_case,
}
# The nhjax methods of the package's registry, by the paper's names (AVF aside: it
# differs from GONZALEZ only in its discrete gradient).
METHODS = {
    method.name: method.solver
    for method in REGISTRY.values()
    if isinstance(method.solver, nh.AbstractMethod) and method.name != "AVF"
}
REGISTRY_BY_NAME = {method.name: method for method in REGISTRY.values()}
ENERGY_PRESERVING = tuple(method.name for method in REGISTRY.values() if method.keeps_energy)
PARAMETRISED = [
    (method, case)
    for method in METHODS
    for case in (("adapted sleigh",) if REGISTRY_BY_NAME[method].adapted else ("gearbox", "sleigh"))
]
# Forward mode on every method for the gearbox, and for the sleigh where the frame and the
# metric depend on q: each case is one more compilation.
FORWARD_MODE = [
    (method, case)
    for method, case in PARAMETRISED
    if case != "sleigh" or method == "GONZALEZ-R"
]


def _gearbox_start():
    _, build, theta, _ = _gearbox_case()
    return build(theta)


def _outputs(case, method, adjoint=None):
    """theta -> F(theta) = (weights . y_N, H(y_N), H(y_0)), and theta."""
    system, build, theta, dt = CASES[case]()

    def outputs(theta):
        y0, args = build(theta)
        solution = nh.integrate(
            system, method, y0, dt, N_STEPS, args=args, save_every=N_STEPS, adjoint=adjoint
        )
        final = jnp.concatenate([y[-1] for y in jax.tree.leaves(solution.ys)])
        weights = jnp.cos(jnp.arange(final.shape[0]) + 1.0)
        return jnp.stack([weights @ final, solution.energy[-1], system.energy(y0, args)])

    return outputs, theta


def _values_and_jacobians(outputs, thetas):
    """F and its reverse-mode Jacobian at each row of `thetas`: one compiled program."""

    def one(theta):
        values, pullback = jax.vjp(outputs, theta)
        (jacobian,) = jax.vmap(pullback)(jnp.eye(values.shape[0], dtype=values.dtype))
        return values, jacobian

    return jax.jit(jax.vmap(one))(thetas)


def _relative(a, b) -> float:
    return float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b)))


@pytest.fixture(scope="module")
def reverse_mode():
    """(method, case) -> (theta, F and its Jacobian at theta, finite-difference Jacobian)."""
    cache = {}

    def get(method_name, case):
        if (method_name, case) not in cache:
            outputs, theta = _outputs(case, METHODS[method_name])
            (d,) = theta.shape
            steps = 1e-5 * (1 + jnp.abs(theta))
            shifts = jnp.diag(steps)
            thetas = jnp.concatenate([theta[None], theta + shifts, theta - shifts])
            values, jacobians = _values_and_jacobians(outputs, thetas)
            differences = (values[1 : d + 1] - values[d + 1 :]) / (2 * steps[:, None])
            cache[method_name, case] = theta, values[0], jacobians[0], differences.T
        return cache[method_name, case]

    return get


@pytest.mark.parametrize("method_name, case", PARAMETRISED)
def test_reverse_mode_matches_finite_differences(reverse_mode, method_name, case):
    """Relative error <= 1e-6 over 200 steps, with respect to the initial
    state and the parameters, under jit and vmap."""
    theta, _, jacobian, differences = reverse_mode(method_name, case)
    assert bool(jnp.all(jnp.isfinite(jacobian)))
    # The trajectory must depend on every component of theta, or the check is empty.
    assert bool(jnp.all(jnp.abs(differences[0]) > 1e-6))
    assert _relative(jacobian[0], differences[0]) <= 1e-6
    assert _relative(jacobian[1], differences[1]) <= 1e-6


@pytest.mark.parametrize("method_name, case", FORWARD_MODE)
def test_forward_mode_matches_reverse_mode(reverse_mode, method_name, case):
    """`jax.jacfwd` with `adjoint=diffrax.ForwardMode()` against `jax.jacrev` (the
    default adjoint)."""
    theta, _, reverse, _ = reverse_mode(method_name, case)
    outputs, _ = _outputs(case, METHODS[method_name], adjoint=diffrax.ForwardMode())
    forward = jax.jit(jax.jacfwd(outputs))(theta)
    assert _relative(forward, reverse) <= 1e-10


@pytest.mark.parametrize("method_name, case", PARAMETRISED)
def test_energy_gradient_is_conserved(reverse_mode, method_name, case):
    """H(y_N(theta)) = H(y_0(theta)) for every theta when a method preserves energy
    exactly, so their gradients agree, with respect to the initial state and to the
    parameters. Methods that do not preserve energy miss this by far more."""
    _, _, jacobian, _ = reverse_mode(method_name, case)
    mismatch = _relative(jacobian[1], jacobian[2])
    if method_name in ENERGY_PRESERVING:
        assert mismatch <= 1e-11
    else:
        assert mismatch >= 1e-6


def test_failed_root_finds_give_nan_derivatives():
    """A run whose root find fails (throw=False) has NaN derivatives: of the final
    state, whose derivative would otherwise be zero (it is a NaN constant), and even of
    the initial save, whose value is finite. Its neighbour in the batch keeps finite
    derivatives."""
    method = nh.GonzalezF(root_find_max_steps=6)
    _, build, theta, _ = _gearbox_case()

    def first_and_last(theta, dt):
        y0, args = build(theta)
        solution = nh.integrate(GEARBOX, method, y0, dt, 20, args=args, throw=False)
        q = solution.ys[0]
        return jnp.stack([jnp.sum(q[0]), jnp.sum(q[-1])]), solution.result

    jacobian, result = jax.jit(jax.vmap(jax.jacrev(first_and_last, has_aux=True)))(
        jnp.stack([theta, theta]), jnp.array([0.01, 1.0])
    )
    assert bool((result == nh.RESULTS.successful)[0])
    assert bool((result == nh.RESULTS.root_find_not_converged)[1])
    assert bool(jnp.all(jnp.isfinite(jacobian[0])))
    assert bool(jnp.all(jnp.isnan(jacobian[1])))


def test_failed_initial_state_gives_nan_derivatives():
    """An initial state that violates the constraint (throw=False): NaN derivatives,
    not the zeros of a NaN constant."""
    _, build, theta, _ = _gearbox_case()

    def initial_save(p):
        (q0, _), args = build(theta)
        solution = nh.integrate(GEARBOX, nh.SIDLA(), (q0, p), 0.1, 5, args=args, throw=False)
        return jnp.sum(solution.ys[1][0]), solution.result

    gradient, result = jax.grad(initial_save, has_aux=True)(jnp.array([1.0, 1.0, 0.0]))
    assert result == nh.RESULTS.constraint_violated_initially
    assert bool(jnp.all(jnp.isnan(gradient)))


def test_failed_run_raises_under_grad_when_throwing():
    y0, args = _gearbox_start()

    def loss(p):
        solution = nh.integrate(GEARBOX, nh.GonzalezF(root_find_max_steps=6), (y0[0], p), 1.0, 20, args=args)
        return jnp.sum(solution.ys[0])

    with pytest.raises(Exception, match="not solved to tolerance"):
        jax.grad(loss)(y0[1])


def test_adjoint_must_be_a_diffrax_adjoint():
    y0, args = _gearbox_start()
    with pytest.raises(ValueError, match="adjoint must be a diffrax adjoint"):
        nh.integrate(GEARBOX, nh.SIDLA(), y0, 0.1, 2, args=args, adjoint="forward")


def _mid_run_saves(adjoint):
    """(p0, dt) -> the states, energies and times of every 8th of 40 GONZALEZ-R steps."""
    (q0, _), args = _gearbox_start()

    def saves(p0, dt):
        solution = nh.integrate(GEARBOX, nh.GonzalezR(), (q0, p0), dt, 40, args=args, save_every=8, adjoint=adjoint)
        return jnp.concatenate([*(y.ravel() for y in solution.ys), solution.energy, solution.ts])

    return saves


def test_replayed_derivatives_match_the_checkpointed_loop():
    """Two routes to the derivatives of mid-run saves, their energies and times, with
    respect to the momentum and dt: the default, replaying the run from its stored roots
    (reverse and forward mode), and diffrax's loop checkpointed at every step, through
    the root finder."""
    (_, p0), _ = _gearbox_start()
    dt = jnp.asarray(0.1)
    checkpointed = jax.jit(jax.jacrev(_mid_run_saves(diffrax.RecursiveCheckpointAdjoint(checkpoints=40)), (0, 1)))
    reverse = jax.jit(jax.jacrev(_mid_run_saves(None), (0, 1)))
    forward = jax.jit(jax.jacfwd(_mid_run_saves(None), (0, 1)))
    expected = checkpointed(p0, dt)
    assert bool(jnp.all(jnp.abs(expected[1][-5:]) > 0))  # the save times depend on dt
    for route in (reverse, forward):
        for got, want in zip(route(p0, dt), expected):
            assert _relative(got, want) <= 1e-10


def test_differentiated_runs_report_what_the_loop_reports():
    """Under differentiation a run is taken by `nhjax._replay`'s own loop; in a batch
    where one trajectory fails at step 24 of 40 (on a save) and one succeeds, it
    returns the run's values, codes, statistics and save times (infinite after
    the last step taken), forward mode applied to the jitted, vmapped run."""
    (q0, p0), args = _gearbox_start()
    method = nh.GonzalezF(root_find_max_steps=12)

    def run(p0, dt):
        return nh.integrate(GEARBOX, method, (q0, p0), dt, 40, args=args, save_every=4, throw=False)

    dts = jnp.array([0.1, 0.6])
    batch = jax.jit(jax.vmap(run, (None, 0)))
    plain = batch(p0, dts)
    # Forward mode of the jitted batch, its momentum not batched: the composition in
    # which a result code or a NaN gate that is constant in one branch of a derivative
    # rule, and batched in the other, fails to batch.
    differentiated, _ = jax.jvp(lambda p: batch(p, dts), (p0,), (jnp.ones_like(p0),))
    assert [int(n) for n in plain.stats["num_steps"]] == [40, 24]
    assert bool((plain.result == nh.RESULTS.successful)[0])
    assert bool((plain.result == nh.RESULTS.root_find_not_converged)[1])
    assert bool(jnp.all(jnp.isinf(plain.ts[1, 7:]))) and bool(jnp.isfinite(plain.ts[1, 6]))
    # The same values, NaN and infinite where the loop's are; finite ones to roundoff
    # (two programs, compiled apart, may round differently).
    for got, want in zip(jax.tree.leaves(differentiated), jax.tree.leaves(plain)):
        assert got.shape == want.shape and got.dtype == want.dtype
        if not jnp.issubdtype(want.dtype, jnp.floating):
            assert bool(jnp.all(got == want))
            continue
        assert bool(jnp.all(jnp.isnan(got) == jnp.isnan(want)))
        assert bool(jnp.all(jnp.isinf(got) == jnp.isinf(want)))
        finite = jnp.isfinite(want)
        assert bool(jnp.all(jnp.abs(got - want)[finite] <= 1e-12 * (1 + jnp.abs(want[finite]))))


def test_runs_of_traced_lengths_in_one_batch_have_the_derivatives_of_their_static_runs():
    """A batch of runs of 30 and 40 steps out of a bound of 40 (saved every 4: step 30
    is saved at its own time, then held): the final state's reverse- and forward-mode
    derivatives with respect to the momentum and dt are those of the runs with their
    step counts static. Reverse mode meets the steps after a run's end, whose replay
    it discards, with a zero cotangent: they must add nothing, not NaN."""
    (q0, p0), args = _gearbox_start()
    method = nh.GonzalezR()

    def final(p0, dt, n, max_steps):
        solution = nh.integrate(GEARBOX, method, (q0, p0), dt, n, args=args, save_every=max_steps // 10,
                                max_steps=max_steps)
        return jnp.concatenate(jax.tree.leaves(jax.tree.map(lambda y: y[-1], solution.ys)))

    dts, ns = jnp.array([0.1, 0.07]), jnp.array([30, 40])
    for differentiate in (jax.jacrev, jax.jacfwd):
        bounded = jax.jit(jax.vmap(differentiate(lambda p, dt, n: final(p, dt, n, 40), (0, 1)), (None, 0, 0)))
        got = bounded(p0, dts, ns)
        for i, n in enumerate((30, 40)):
            want = differentiate(lambda p, dt: final(p, dt, n, n), (0, 1))(p0, dts[i])
            for g, w in zip(got, want):
                assert _relative(g[i], w) <= 1e-12


def test_forward_over_forward_second_derivatives_match_finite_differences():
    """The Hessian by `jax.jacfwd(jax.jacfwd(...))` through 5 GONZALEZ-R steps (the
    predictor's carry and the Gonzalez correction included), against central
    differences of the gradient: the root's implicit derivative is itself
    differentiated with the root moving with the data."""
    _, build, theta, dt = _gearbox_case()

    def loss(theta):
        y0, args = build(theta)
        solution = nh.integrate(GEARBOX, nh.GonzalezR(), y0, dt, 5, args=args, save_every=5)
        return jnp.sum(solution.ys[0][-1] ** 2) + jnp.sum(jnp.sin(solution.ys[1][-1]))

    gradient = jax.jit(jax.grad(loss))
    steps = 1e-5 * (1 + jnp.abs(theta))
    differences = jnp.stack(
        [(gradient(theta + s) - gradient(theta - s)) / (2 * s[i]) for i, s in enumerate(jnp.diag(steps))]
    )
    for second in (jax.jacfwd(jax.jacfwd(loss)), jax.jacrev(jax.jacfwd(loss))):
        assert _relative(jax.jit(second)(theta), differences) <= 1e-7


def test_reverse_mode_inside_second_derivatives_are_nan_not_wrong():
    """`jax.hessian` (forward over reverse) and reverse over reverse lose each step's
    implicit derivative in JAX's partial evaluation of the loop: they are NaN, where
    they used to be finite and wrong. First derivatives of the same loss stay finite."""
    _, build, theta, dt = _gearbox_case()

    def loss(theta):
        y0, args = build(theta)
        solution = nh.integrate(GEARBOX, nh.SIDLA(), y0, dt, 5, args=args, save_every=5)
        return jnp.sum(solution.ys[0][-1] ** 2)

    assert bool(jnp.all(jnp.isfinite(jax.grad(loss)(theta))))
    for second in (jax.hessian(loss), jax.jacrev(jax.grad(loss))):
        assert bool(jnp.all(jnp.isnan(jax.jit(second)(theta))))


def test_derivatives_replay_runs_whose_roots_fit_the_budget():
    from nhjax._adjoints import CHECKPOINT_BUDGET_BYTES, replays_derivatives

    y0, args = _gearbox_start()
    dt = jnp.asarray(0.1)
    per_step_floor = sum(leaf.nbytes for leaf in y0)
    assert replays_derivatives(GEARBOX, nh.GonzalezR(), y0, args, dt, 1000)
    too_many = CHECKPOINT_BUDGET_BYTES // per_step_floor + 1
    assert not replays_derivatives(GEARBOX, nh.GonzalezR(), y0, args, dt, too_many)
    # A composition takes several root finds per step: diffrax's checkpointed loop.
    assert not replays_derivatives(GEARBOX, nh.Composition(nh.SIDLA(), 4), y0, args, dt, 10)


def test_runs_beyond_the_replay_budget_are_differentiated_through_the_checkpointed_loop(monkeypatch):
    """Where the roots would not fit the budget, `integrate`'s derivative rule
    differentiates diffrax's loop with `default_adjoint` instead of the replay: the
    same gradient as the replay's; forward mode there is refused, as for any
    checkpointed loop."""
    import nhjax._adjoints as adjoints

    (q0, p0), args = _gearbox_start()
    dt = jnp.asarray(0.1)
    # The same system as a new object, so that its runs are traced afresh (the budget is
    # read when a run is traced) and no other test meets their programs.
    same_gearbox = nh.NonholonomicSystem(
        lambda q, p, args: GEARBOX.hamiltonian(q, p, args), lambda q, args: GEARBOX.constraints(q, args)
    )

    def loss(system, p0):
        solution = nh.integrate(system, nh.GonzalezR(), (q0, p0), dt, 33, args=args, save_every=11)
        return jnp.sum(solution.ys[0][-1] ** 2) + jnp.sum(jnp.sin(solution.ys[1]))

    replayed = jax.grad(loss, argnums=1)(GEARBOX, p0)
    monkeypatch.setattr(adjoints, "CHECKPOINT_BUDGET_BYTES", 1024)
    assert not adjoints.replays_derivatives(same_gearbox, nh.GonzalezR(), (q0, p0), args, dt, 33)
    checkpointed = jax.grad(loss, argnums=1)(same_gearbox, p0)
    assert _relative(checkpointed, replayed) <= 1e-12
    with pytest.raises(TypeError, match="custom_vjp"):
        jax.jacfwd(loss, argnums=1)(same_gearbox, p0)


def test_float32_derivatives_agree_with_float64():
    """Reverse mode through 20 GONZALEZ-R steps from a float32 start: float32
    derivatives, within a few float32 ulps (relative to the largest) of the float64
    ones."""
    y0, args = _gearbox_start()

    def loss(p0, dtype):
        start = jax.tree.map(lambda y: y.astype(dtype), (y0[0], p0))
        solution = nh.integrate(GEARBOX, nh.GonzalezR(), start, 0.1, 20, args=args, save_every=20)
        return jnp.sum(solution.ys[0][-1] ** 2) + jnp.sum(jnp.cos(solution.ys[1][-1]))

    single = jax.grad(loss)(y0[1].astype(jnp.float32), jnp.float32)
    double = jax.grad(loss)(y0[1], jnp.float64)
    assert single.dtype == jnp.float32
    assert _relative(single.astype(jnp.float64), double) <= 100 * float(jnp.finfo(jnp.float32).eps)


def test_default_adjoint_checkpoints_every_step_within_its_budget():
    from nhjax._adjoints import CHECKPOINT_BUDGET_BYTES, default_adjoint

    y0, args = _gearbox_start()
    dt = jnp.asarray(0.1)
    per_step_floor = sum(leaf.nbytes for leaf in y0)  # the state alone; the method adds its own
    assert default_adjoint(GEARBOX, nh.GonzalezR(), y0, args, dt, 1000).checkpoints == 1000
    too_many = CHECKPOINT_BUDGET_BYTES // per_step_floor + 1
    assert default_adjoint(GEARBOX, nh.GonzalezR(), y0, args, dt, too_many).checkpoints is None
    # GONZALEZ-R carries more than the state from step to step, and that counts too.
    fewer = CHECKPOINT_BUDGET_BYTES // (2 * per_step_floor)
    assert default_adjoint(GEARBOX, nh.GonzalezR(), y0, args, dt, fewer).checkpoints is None


def test_a_replayed_gonzalez_r_step_stores_its_state_frame_coordinates_signs_and_root():
    """Per step, a run's derivative keeps what its replay reads: the state (q, p), 2n
    numbers; the carried zeta' = (q', rho'), 2n - k, and the frame's k signs; the root,
    2n - k. The predictor's velocities, step sizes and displacement history, which only
    guess the root, are not kept (they were 42 of the sleigh's 59 numbers)."""
    from nhjax._replay import replay_storage_bytes

    sleigh = nh.examples.chaplygin_sleigh()
    y0 = sleigh.from_adapted(jnp.array([0.0, 0.0, 0.1, 0.3, -0.6]), sleigh.args)
    n, k = y0[0].shape[0], 1
    kept = 2 * n + (2 * n - k) + k + (2 * n - k)
    assert replay_storage_bytes(sleigh.canonical, nh.GonzalezR(), y0, sleigh.args, jnp.asarray(0.1)) == 8 * kept


def test_derivatives_replayed_in_chunks_are_those_of_one_scan(monkeypatch):
    """The recording's and the replay's scans in chunks of steps (the sleigh's 60 steps
    recorded in chunks of 12, its 10 blocks of 6 steps between saves replayed in chunks
    of 2 blocks) give the reverse- and forward-mode derivatives of the plain scans
    (`SEQUENTIAL_BYTES` 0: no chunks), to roundoff."""
    import nhjax._chunked_scan as chunked_scan

    sleigh = nh.examples.chaplygin_sleigh()
    y0 = sleigh.from_adapted(jnp.array([0.0, 0.0, 0.1, 0.3, -0.6]), sleigh.args)

    def loss(p0):
        ys = nh.integrate(sleigh.canonical, nh.GonzalezR(), (y0[0], p0), 0.1, 60, args=sleigh.args, save_every=6).ys
        return jnp.sum(ys[0] ** 2) + jnp.sum(jnp.cos(ys[1]))

    def scans(jaxpr):
        return sum(1 for e in equations(jaxpr) if e.primitive.name == "scan")

    def derivatives():
        # Compiled again, not taken from the caches of the other configuration.
        jax.clear_caches()
        count = scans(jax.make_jaxpr(jax.grad(loss))(y0[1]).jaxpr)
        return count, jax.jit(jax.grad(loss))(y0[1]), jax.jit(jax.jacfwd(loss))(y0[1])

    from .helpers import equations

    chunked_scans, chunked_reverse, chunked_forward = derivatives()
    monkeypatch.setattr(chunked_scan, "SEQUENTIAL_BYTES", 0)
    plain_scans, reverse, forward = derivatives()
    assert chunked_scans > plain_scans
    assert _relative(chunked_reverse, reverse) <= 1e-13
    assert _relative(chunked_forward, forward) <= 1e-13
    assert _relative(chunked_reverse, chunked_forward) <= 1e-10
