"""GONZALEZ-R: energy across frame changes, agreement with the reduced method, the
chord matrix (held frame and exact) and the predictor, the finite-difference option, the metric shortcuts, and
rank loss. (Order, invariants and symmetry: test_methods.py.)"""

import pathlib
import sys

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh
from nhjax._solver.base import HISTORY

from ..helpers import canonical_starts, equations, final_states, fitted_order, relative_energy_error


sys.path.insert(0, str(pathlib.Path(__file__).parents[2] / "benchmarks"))
import scaling  # noqa: E402


GEARBOX = nh.examples.gearbox()
METHOD = nh.GonzalezR()
FINITE_DIFFERENCE = nh.GonzalezR(derivative="central_difference")
STEP_SIZES = (0.2, 0.1, 0.05)


STARTS = canonical_starts()


def test_energy_across_changes_of_the_frame_signs():
    """A step starts from the previous step's reduced state, except where the frame's
    sign choices change (then from (q, p)): the sleigh's turning crosses such changes,
    and energy holds across them."""
    example, y0 = STARTS["sleigh, q-dependent M"]
    system = example.canonical
    solution = nh.integrate(system, METHOD, y0, 0.1, 2_000, args=example.args)
    signs = jax.vmap(lambda q: system.frame_signs(q, example.args))(solution.ys[0])
    assert int(jnp.sum(jnp.any(signs[1:] != signs[:-1], axis=1))) >= 1
    assert relative_energy_error(solution) <= 1e-13
    assert float(jnp.max(jnp.abs(solution.constraint))) <= 1e-13


def _canonical_and_adapted_end_states(example, y0, t1, step_sizes):
    """For each step size, the max distance at t1 between GONZALEZ-R on the canonical
    system and DiscreteGradient on the example's adapted form, mapped back."""
    x0 = example.to_adapted(*y0, example.args)
    canonical = final_states(example.canonical, METHOD, y0, t1, step_sizes, example.args)
    adapted = final_states(example.adapted, nh.DiscreteGradient(), x0, t1, step_sizes, example.args)
    distances = []
    for (q_canonical, p_canonical), x in zip(canonical, adapted):
        q, p = example.from_adapted(x, example.args)
        distances.append(max(float(jnp.max(jnp.abs(q_canonical - q))), float(jnp.max(jnp.abs(p_canonical - p)))))
    return distances


def test_agrees_with_the_analytic_reduced_method_at_order_two():
    """On the quartic, GONZALEZ-R on the canonical system and DiscreteGradient on the
    paper's analytic adapted form (fcseq) are different second-order discretisations of
    one flow (different frames of D), so their end states differ by O(h^2)."""
    example, y0 = STARTS["quartic, n = 7"]
    differences = _canonical_and_adapted_end_states(example, y0, 5.0, STEP_SIZES)
    assert 1.8 <= fitted_order(STEP_SIZES, differences) <= 2.2, differences


@pytest.mark.parametrize("name", ["sleigh, q-dependent M", "disk, k = 2"])
def test_equals_the_analytic_reduced_method_where_the_reduced_energy_is_quadratic(name):
    """For the sleigh and the disk, V = 0 and the frame's Gram matrix X^T M X is constant
    in both frames, so the reduced Hamiltonian is a quadratic form in rho alone. The
    Gonzalez discrete gradient of a quadratic is its midpoint gradient, and the
    midpoint-gradient method is covariant under linear changes of the rho coordinates:
    the two routes give the same trajectory, to roundoff."""
    example, y0 = STARTS[name]
    assert _canonical_and_adapted_end_states(example, y0, 20.0, (0.1,))[0] <= 1e-12


def test_one_step_is_the_discrete_gradient_method_on_the_reduced_system():
    """Within one step the sign choices are fixed, so GONZALEZ-R is DiscreteGradient
    (autodiff gradient of H(q, p(q, rho))) on `system.reduced(signs)`, mapped back."""
    example, y0 = STARTS["sleigh, q-dependent M"]
    system, args = example.canonical, example.args
    signs = system.frame_signs(y0[0], args)
    zeta = system.to_reduced(y0, args, signs)
    reduced = nh.integrate(system.reduced(signs), nh.DiscreteGradient(), zeta, 0.1, 1, args=args)
    # The first step of the run of test_energy_across_changes_of_the_frame_signs: the
    # same program.
    direct = nh.integrate(system, METHOD, y0, 0.1, 2_000, args=args)
    q, p = system.from_reduced(reduced.ys[-1], args, signs)
    np.testing.assert_allclose(direct.ys[0][1], q, atol=1e-15)
    np.testing.assert_allclose(direct.ys[1][1], p, atol=1e-15)


@pytest.mark.parametrize("name", list(STARTS))
def test_chord_matrix_contracts_like_h(name):
    """The chord matrix C (the frame held to first order and turned along the velocity,
    `GonzalezR.chord_jacobian`)
    against the Jacobian J of the simplified residual by `jax.jacfwd`, at the initial
    guess of a step: the chord iteration contracts by the norm of I - C^{-1}J, O(h)
    for what the matrix leaves out (its exact form would give O(h^3)): a few per cent
    at h = 0.1 and at least 1.8 times less at h = 0.05, except where the matrix is
    exact (the gearbox and the disk, whose frames turn only out of D). I - J itself
    is O(h)."""
    example, y0 = STARTS[name]

    @eqx.filter_jit  # one program, not hundreds of operations dispatched one by one
    def contraction(system, h, y0, args):
        guess, data = METHOD.setup(system, 0.0, h, y0, args, METHOD.initial_carry(system, y0, args))
        exact = jax.jacfwd(METHOD.simplified_residual)(guess, data)
        iteration = jnp.eye(guess.shape[0]) - jnp.linalg.solve(METHOD.chord_jacobian(guess, data), exact)
        return jnp.max(jnp.abs(iteration)), jnp.max(jnp.abs(exact - jnp.eye(guess.shape[0])))

    factors, sizes = zip(*(contraction(example.canonical, jnp.asarray(h), y0, example.args) for h in (0.1, 0.05)))
    assert float(factors[0]) <= 0.1, (factors, sizes)
    assert float(factors[0]) <= 0.5 * float(sizes[0]), (factors, sizes)
    if factors[0] > 1e-10:
        assert float(factors[0] / factors[1]) >= 1.8, factors


def test_the_frame_turn_sets_the_chord_iterations_contraction():
    """The spectral radius of the chord iteration I - C^{-1}J at a step's first guess
    (J by `jax.jacfwd`), with and without the frame's turn along the velocity in C
    (`ReducedSystem.field_jacobian`): where the frame turns within D (the quartic, and
    the synthetic system of `benchmarks/scaling.py` with n = 8, whose two constraint
    rows turn with the configuration) the turn cuts it at least fivefold, and on the
    quartic it leaves an iteration that contracts faster than O(h); where it turns
    only out of D (the gearbox) both matrices are exact. Without the turn the radius
    is O(h)."""
    cases = {"synthetic n = 8": (scaling.SYSTEM, scaling.initial_state(8), None)}
    for name in ("quartic", "gearbox"):
        example = nh.examples.EXAMPLES[name]()
        cases[name] = (example.canonical, example.start("canonical"), example.args)

    @eqx.filter_jit
    def radii(system, h, y0, args):
        guess, data = METHOD.setup(system, 0.0, h, y0, args, METHOD.initial_carry(system, y0, args))
        exact = jax.jacfwd(METHOD.simplified_residual)(guess, data)
        identity = jnp.eye(guess.shape[0])
        radius = []
        for frame_turn in (False, True):
            field = data.reduced.field_jacobian(
                data.zeta + 0.5 * data.scale * guess, data.midpoint_time, args, frame_turn=frame_turn
            )
            chord = identity - (h / data.scale)[:, None] * field * (0.5 * data.scale)[None, :]
            radius.append(jnp.max(jnp.abs(jnp.linalg.eigvals(identity - jnp.linalg.solve(chord, exact)))))
        return radius

    for name, (system, y0, args) in cases.items():
        (held, turned), (held_half, turned_half) = (
            [float(r) for r in radii(system, jnp.asarray(h), y0, args)] for h in (0.1, 0.05)
        )
        if name == "gearbox":
            assert max(held, turned, held_half, turned_half) < 1e-12, name
            continue
        assert 1.8 <= held / held_half <= 2.2, (name, held, held_half)
        assert turned <= held / 5 and turned_half <= held_half / 5, (name, held, turned)
        if name == "quartic":
            assert turned / turned_half >= 3.5, (turned, turned_half)


def test_the_exact_chord_matrix_finds_the_same_steps_in_fewer_iterations():
    """On a tractor pulling 3 trailers (k = 4 of n = 6: the frame of D turns fast within
    it), `exact_chord_matrix=True` takes the same steps to roundoff in fewer than half
    the iterations of the matrix with the frame held; anything but a bool or `None`
    is refused."""
    train = nh.examples.tractor_trailers(3)
    y0 = train.initial_state()
    # Each matrix formed at every step: a kept one would be a step old.
    methods = {exact: nh.GonzalezR(exact_chord_matrix=exact, reuse_chord_matrix=False) for exact in (False, True)}
    runs = {
        exact: nh.integrate(train.canonical, method, y0, 0.1, 20, args=train.args) for exact, method in methods.items()
    }
    for held, exact in zip(runs[False].ys, runs[True].ys):
        np.testing.assert_allclose(exact, held, rtol=0, atol=1e-11)
    iterations = {exact: float(run.stats["root_find_steps"]) / 20 for exact, run in runs.items()}
    assert iterations[True] < 0.5 * iterations[False] and iterations[True] < 5, iterations
    with pytest.raises(ValueError, match="exact_chord_matrix must be None, True or False"):
        nh.GonzalezR(exact_chord_matrix="yes")

    # By default: exact where the metric depends on q and the matrix is kept.
    def exact_by_default(method, example, start):
        carry = method.initial_carry(example.canonical, start, example.args)
        data = method.setup(example.canonical, 0.0, 0.1, start, example.args, carry)[1]
        return method.uses_exact_chord_matrix(data)

    gearbox = nh.examples.gearbox()
    assert exact_by_default(nh.GonzalezR(), train, y0)
    assert not exact_by_default(nh.GonzalezR(reuse_chord_matrix=False), train, y0)
    assert not exact_by_default(nh.GonzalezR(), gearbox, gearbox.start("canonical"))


@pytest.mark.parametrize("case", ["Euler's disk", "5 trailers"])
def test_the_exact_chord_matrix_is_the_residuals_jacobian(case):
    """`exact_chord_matrix=True`'s matrix, by forward differences of the simplified
    residual (a column at a time for Euler's disk, N = 8; batched for a tractor with 5
    trailers, N = 10), is that residual's Jacobian by `jax.jacfwd` to 1e-6 of its
    size, at the first step's guess."""
    if case == "Euler's disk":
        example = nh.examples.rolling_disk_3d()
        system, y0, h = example.canonical, example.initial_state(), 0.01
    else:
        example = nh.examples.tractor_trailers(5)
        system, y0, h = example.canonical, example.initial_state(), 0.1
    method = nh.GonzalezR(exact_chord_matrix=True)
    carry = method.initial_carry(system, y0, example.args)
    guess, data = method.setup(system, 0.0, h, y0, example.args, carry)
    assert method._columnwise(guess, data) == (case == "Euler's disk")
    differenced = eqx.filter_jit(method.chord_jacobian)(guess, data)
    exact = eqx.filter_jit(lambda u, d: jax.jacfwd(method.simplified_residual)(u, d))(guess, data)
    error = float(jnp.max(jnp.abs(differenced - exact)))
    assert error <= 1e-6 * float(jnp.max(jnp.abs(exact))), error


def test_predictor_is_third_order_once_two_steps_are_known_and_of_order_history_plus_one_after_history():
    """The guess of a step against its root: O(h^2) at the first step (explicit Euler's
    order), O(h^3) once two steps are known (the last mean velocity extrapolated from
    the two before), and O(h^(HISTORY + 1)) once HISTORY steps of one size are (the
    polynomial through the last step ends)."""
    example, y0 = STARTS["sleigh, q-dependent M"]
    system, args = example.canonical, example.args

    @eqx.filter_jit
    def guess_error_and_step(h, t0, y, state):
        guess, data = METHOD.setup(system, 0.0, h, y, args, state.carry)
        y, _, _, state, result = METHOD.step(system, t0, t0 + h, y, args, state, False)
        increment = state.carry.zeta - data.zeta
        return jnp.max(jnp.abs(data.scale * guess - increment)), y, state, result

    errors = []
    for h in STEP_SIZES:
        h = jnp.asarray(h)
        state, y = METHOD.init(system, 0.0, h, y0, args), y0
        errors.append([])
        for step in range(HISTORY + 3):
            error, y, state, result = guess_error_and_step(h, step * h, y, state)
            assert result == diffrax.RESULTS.successful
            errors[-1].append(float(error))
    errors = np.array(errors)
    assert fitted_order(STEP_SIZES, errors[:, 0]) <= 2.2, errors
    assert 2.8 <= fitted_order(STEP_SIZES, errors[:, 3]) <= 3.5, errors
    assert fitted_order(STEP_SIZES, errors[:, HISTORY + 2]) >= HISTORY + 0.5, errors


def test_finite_difference_option_agrees_at_order_two():
    example, y0 = STARTS["gearbox, M = I"]
    exact = final_states(example.canonical, METHOD, y0, 5.0, STEP_SIZES)
    finite = final_states(example.canonical, FINITE_DIFFERENCE, y0, 5.0, STEP_SIZES)
    differences = [float(jnp.max(jnp.abs(a[1] - b[1]))) for a, b in zip(exact, finite)]
    assert 1.8 <= fitted_order(STEP_SIZES, differences) <= 2.2, differences
    long = nh.integrate(example.canonical, FINITE_DIFFERENCE, y0, 0.1, 10_000, save_every=100)
    assert relative_energy_error(long) <= 1e-13
    assert float(jnp.max(jnp.abs(long.constraint))) <= 1e-13


def test_an_increment_that_cannot_work_is_named():
    """A zero, negative or non-finite increment (zero gave NaN steps), and an increment
    with `derivative="autodiff"`, which would ignore it, are refused when the method
    or the reduced system is made; a traced increment is taken as it is."""
    example, y0 = STARTS["gearbox, M = I"]
    signs = example.canonical.frame_signs(y0[0], example.args)
    for step in (0.0, -1e-3, float("nan"), jnp.inf, jnp.array([1e-3, 1e-3])):
        with pytest.raises(ValueError, match="difference_step must be a positive finite number"):
            nh.GonzalezR(derivative="central_difference", difference_step=step)
        with pytest.raises(ValueError, match="difference_step must be a positive finite number"):
            example.canonical.reduced(signs, "central_difference", step)
    with pytest.raises(ValueError, match='difference_step is the increment of derivative="central_difference"'):
        nh.GonzalezR(difference_step=1e-3)
    traced = jax.jit(lambda step: nh.GonzalezR(derivative="central_difference", difference_step=step).difference_step)
    assert float(traced(1e-3)) == 1e-3


def test_gearbox_partial_energies_drift_at_order_two_while_the_total_is_exact():
    """H3 (the pendulum) and H - H3 are each conserved by the exact flow (A has no q3
    column and V separates, paper §4.4); the discrete gradient of the total mixes them,
    at O(h^2)."""
    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    steps = [round(20.0 / h) for h in STEP_SIZES]
    drifts = []
    for h, n in zip(STEP_SIZES, steps):
        # The same number of steps at every h, so that one program serves them all
        # (dt is traced); each check reads the saves up to t = 20.
        solution = nh.integrate(GEARBOX.canonical, METHOD, y0, h, max(steps))
        energy = solution.energy[: n + 1]
        pendulum = GEARBOX.pendulum_energy(*(y[: n + 1] for y in solution.ys))
        drifts.append(float(jnp.max(jnp.abs(pendulum - pendulum[0]))))
        assert float(jnp.max(jnp.abs(energy / energy[0] - 1))) <= 1e-13
        np.testing.assert_allclose(energy - pendulum, energy[0] - pendulum[0], atol=drifts[-1] * 1.001)
    assert drifts[-1] > 1e-8  # visibly not conserved ...
    assert 1.8 <= fitted_order(STEP_SIZES, drifts) <= 2.2, drifts  # ... but at order 2


def test_constraint_losing_rank_is_reported_per_trajectory():
    """A(q) = (1 - q3)(1, 1/2, 0) loses rank at q3 = 1. q3 is a free rotation, so
    q3 = q3(0) + t p3 to roundoff, and from q3(0) = 1/2 with p3 = 1 and h = 0.1 the fifth
    step lands on q3 = 1: that trajectory fails with its own code; the other one in the
    batch is untouched."""
    def hamiltonian(q, p, args):
        return 0.5 * (p @ p + q[0] ** 2 + q[1] ** 2)

    def constraints(q, args):
        return (1.0 - q[2]) * jnp.array([[1.0, 0.5, 0.0]])

    system = nh.NonholonomicSystem(hamiltonian, constraints)

    def run(q3):
        q = jnp.array([0.1, 0.2, q3])
        p = system.project_momentum(q, jnp.array([0.5, -0.5, 1.0]))
        return nh.integrate(system, METHOD, (q, p), 0.1, 20, throw=False)

    batch = jax.vmap(run)(jnp.array([0.5, -3.0]))
    assert bool((batch.result == nh.RESULTS.constraints_rank_deficient)[0])
    assert bool((batch.result == nh.RESULTS.successful)[1])
    assert bool(jnp.all(jnp.isfinite(batch.ys[0][0, :5])))
    assert not bool(jnp.any(jnp.isfinite(batch.ys[0][0, 5:])))
    single = run(-3.0)
    np.testing.assert_allclose(batch.ys[1][1], single.ys[1], atol=1e-14)
    start = jax.tree.map(lambda y: y[0, 0], batch.ys)
    with pytest.raises(Exception, match="full row rank"):
        nh.integrate(system, METHOD, start, 0.1, 20)


def test_float32():
    example, y0 = STARTS["gearbox, M = I"]
    y0 = jax.tree.map(lambda y: y.astype(jnp.float32), y0)
    solution = nh.integrate(example.canonical, METHOD, y0, 0.1, 1000, save_every=10)
    assert solution.ys[0].dtype == jnp.float32
    eps = float(jnp.finfo(jnp.float32).eps)
    assert relative_energy_error(solution) <= 100 * eps
    assert float(jnp.max(jnp.abs(solution.constraint))) <= 100 * eps


def _losing_rank(second_row):
    """k = 2 constraints whose second row loses rank where q4 crosses 0, near t = 1.59
    from the state below (q4 falls through 0 at a steady pace)."""

    def hamiltonian(q, p, args):
        return 0.5 * p @ p + 0.5 * (q[0] ** 2 + q[1] ** 2 + q[2] ** 2) - jnp.cos(q[3])

    def constraints(q, args):
        return jnp.stack([jnp.array([1.0, 0.0, 1.0, 0.0]), second_row(q)])

    system = nh.NonholonomicSystem(hamiltonian, constraints)
    q0 = jnp.array([0.2, 0.1, -0.1, 0.5])
    return system, (q0, system.project_momentum(q0, jnp.array([0.3, 0.2, -0.1, 0.0])))


@pytest.mark.parametrize(
    "second_row",
    [
        lambda q: jnp.array([1.0, q[3], 1.0, q[3] ** 2]),  # rank lost only at q4 = 0 itself
        lambda q: jnp.array([1.0, q[3], 1.0, 0.0]),  # the frame flips across q4 = 0
    ],
    ids=["smooth-distribution", "flipping-frame"],
)
def test_rank_lost_between_steps_is_reported_at_its_time(second_row):
    """A steps over the point where A loses rank, so no pivot at a step's end need be
    small; the frame with the step's signs degenerates across the step, and the code
    says so at the crossing, at every step size, rather than a root find that does not
    converge (or, depending on rounding, no failure at all)."""
    system, y0 = _losing_rank(second_row)
    steps = jnp.array([0.05, 0.01, 0.002])

    def first_failure_time(dt):
        solution = nh.integrate(system, METHOD, y0, dt, 1000, throw=False)
        finite = jnp.all(jnp.isfinite(solution.ys[0]), axis=1)
        return solution.result, solution.ts[jnp.argmin(finite)]

    results, times = jax.vmap(first_failure_time)(steps)
    assert bool(jnp.all(results == nh.RESULTS.constraints_rank_deficient))
    crossing = 1.59  # where q4 = 0, to about 0.01
    np.testing.assert_allclose(times, crossing, atol=0.06)
    with pytest.raises(RuntimeError, match=r"failed at step 1[56]\d of 200 \(t = 1.5\d+ to 1.[56]\d*\): The constraint matrix A\(q\) lost full row rank"):
        nh.integrate(system, METHOD, y0, 0.01, 200)


def _gearbox_with_kinetic(kinetic):
    """The gearbox's potential and constraint with the kinetic energy `kinetic(q, p, args)`."""
    return nh.NonholonomicSystem(
        lambda q, p, args: kinetic(q, p, args) + GEARBOX.potential(q), GEARBOX.canonical.constraints
    )


_DIAGONAL = jnp.array([1.0, 2.0, 0.5])
_METRIC_ROUTES = {
    "identity": (_gearbox_with_kinetic(lambda q, p, args: 0.5 * p @ p), None),
    "identity, through q": (_gearbox_with_kinetic(lambda q, p, args: 0.5 * p @ p * (1 + 0 * q[0])), None),
    "constant": (_gearbox_with_kinetic(lambda q, p, args: 0.5 * p @ (_DIAGONAL * p)), None),
    "constant, from args": (_gearbox_with_kinetic(lambda q, p, args: 0.5 * p @ (args * p)), _DIAGONAL),
    "constant, through q": (
        _gearbox_with_kinetic(lambda q, p, args: 0.5 * p @ (_DIAGONAL * p) * (1 + 0 * q[0])),
        None,
    ),
}


def test_the_metric_is_found_from_the_program():
    """M = I and a constant M known when tracing are used as constants, a metric read from
    `args` is computed once per step, and one the program computes from q (here through a
    term that vanishes: the analysis is structural) at every evaluation."""
    from nhjax._reduced import metric_of

    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    found = {name: metric_of(system, y0, args) for name, (system, args) in _METRIC_ROUTES.items()}
    assert found["identity"] == "identity"
    assert found["identity, through q"] == "position"
    assert found["constant, through q"] == "position"
    np.testing.assert_array_equal(found["constant"], jnp.diag(1 / _DIAGONAL))
    np.testing.assert_allclose(found["constant, from args"], jnp.diag(1 / _DIAGONAL), rtol=1e-15)


@pytest.mark.parametrize("metric", ["identity", "constant"])
def test_the_metric_shortcuts_give_the_general_method(metric):
    """The shortcuts compute the same method: equal to roundoff over 200 steps to the
    run that evaluates M(q) at every point, with energy and constraint exact."""
    key = jax.random.key(3)
    y0 = GEARBOX.random_initial_state(key)
    if metric == "constant":
        q, p = y0
        y0 = (q, _METRIC_ROUTES["constant"][0].project_momentum(q, p))
    routes = [name for name in _METRIC_ROUTES if name.startswith(metric)]
    runs = {
        name: nh.integrate(_METRIC_ROUTES[name][0], METHOD, y0, 0.1, 200, args=_METRIC_ROUTES[name][1])
        for name in routes
    }
    general = runs[f"{metric}, through q"]
    for name, solution in runs.items():
        assert solution.result == nh.RESULTS.successful
        assert relative_energy_error(solution) <= 1e-13
        assert float(jnp.max(jnp.abs(solution.constraint))) <= 1e-13
        for leaf, general_leaf in zip(solution.ys, general.ys):
            np.testing.assert_allclose(leaf, general_leaf, rtol=0, atol=1e-12, err_msg=name)


def _calls(jaxpr, name: str) -> int:
    """How many calls of the jitted function `name` a jaxpr makes, in its sub-jaxprs too."""
    return sum(
        equation.primitive.name in ("pjit", "jit") and equation.params.get("name") == name
        for equation in equations(jaxpr)
    )


def test_a_step_starts_from_one_factorisation():
    """A step's start takes its frame signs, its reduced state and its momentum from one
    factorisation of A(q)^T (`NonholonomicSystem.stable_frame`), as does the run's first
    carry: Euler's disk, whose metric depends on q (the momentum needs the frame)."""
    example = nh.examples.rolling_disk_3d()
    system = example.canonical
    y0 = example.state(**scaling.DISK_START)
    carry = METHOD.initial_carry(system, y0, example.args)

    def setup(y, carry):
        guess, data = METHOD.setup(system, 0.0, 0.01, y, example.args, carry)
        return guess, data.zeta, data.energy, data.momentum

    assert _calls(jax.make_jaxpr(setup)(y0, carry).jaxpr, "_reflectors") == 1
    first = jax.make_jaxpr(lambda y: METHOD.initial_carry(system, y, example.args))(y0)
    assert _calls(first.jaxpr, "_reflectors") == 1
