"""The chord root finder: convergence, divergence, and stalls at the rounding floor, by
its own loop (`PresetChord.solve`, what the methods use) and through
`optimistix.root_find`, which must agree."""

import pathlib
import re
import sys

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import nhjax as nh
from nhjax._linalg import inverse, is_diagonally_dominant, SEQUENTIAL_BYTES
from nhjax._solver import chord
from nhjax._solver.chord import chord_inverse, ChordSolution, PresetChord, STALL_FACTOR


sys.path.insert(0, str(pathlib.Path(__file__).parents[2] / "benchmarks"))
from _profile import hlo_counts  # noqa: E402


ATOL = 1e-10
ROOT = jnp.array([0.3, -1.2, 2.0])
ROUTES = ["own loop", "optimistix"]


def _through_optimistix(fn, y0, args, inverse, max_steps) -> ChordSolution:
    solution = optx.root_find(
        fn, PresetChord(atol=ATOL), y0, args, options={"inverse": inverse}, max_steps=max_steps, throw=False
    )
    return ChordSolution(solution.value, solution.result, solution.stats["num_steps"], solution.state.residual_size)


def _solve(fn, inverse, max_steps=30, route="own loop", y0=None) -> ChordSolution:
    y0 = jnp.zeros(3) if y0 is None else y0
    if route == "optimistix":
        return _through_optimistix(fn, y0, None, inverse, max_steps)
    return PresetChord(atol=ATOL).solve(fn, y0, None, inverse, max_steps)


@pytest.fixture(params=ROUTES)
def route(request):
    return request.param


def _floor_residual(amplitude):
    """u - ROOT plus an error of size `amplitude` whose sign follows the side of the root:
    the chord iterates then circle the root in a 2-cycle, as they do when a residual's
    rounding error is of the size of the tolerance."""
    return lambda u, args: u - ROOT + amplitude * jnp.where(u > ROOT, 1.0, -1.0)


def test_contracting_iteration_converges_to_tolerance(route):
    solution = _solve(lambda u, args: u - ROOT + 0.05 * jnp.sin(u - ROOT), jnp.eye(3), route=route)
    assert solution.result == optx.RESULTS.successful
    np.testing.assert_allclose(solution.value, ROOT, rtol=0, atol=ATOL)


def test_stall_at_the_rounding_floor_is_accepted_within_the_floor(route):
    """Corrections and residuals of 3 tolerances that never shrink: the plain test never
    passes, the stall test accepts the iterate, which is within the error's size."""
    amplitude = 1.5 * ATOL
    solution = _solve(_floor_residual(amplitude), jnp.eye(3), route=route)
    assert solution.result == optx.RESULTS.successful
    assert int(solution.steps) <= 4
    np.testing.assert_allclose(solution.value, ROOT, rtol=0, atol=amplitude * (1 + 1e-6))


def test_a_stall_is_read_through_the_inverse_where_it_amplifies_the_rounding(route):
    """An ill-conditioned chord matrix (an inverse with a row of absolute sum 101)
    turns a residual at 1.5 tolerances into corrections of about 300 tolerances: the
    iterates circle the root in a 4-cycle, the residual at 3 tolerances. The stall is
    accepted (in units of what a residual at its tolerance moves the iterate by), and
    the iterate is within STALL_FACTOR of those units of the root, component by
    component."""
    jacobian = jnp.array([[1.0, 100.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    amplitude = 1.5 * ATOL
    inverse = jnp.linalg.inv(jacobian)

    def residual(u, args):
        return jacobian @ (u - ROOT) + amplitude * jnp.where(u > ROOT, 1.0, -1.0)

    solution = _solve(residual, inverse, route=route)
    assert solution.result == optx.RESULTS.successful
    assert int(solution.steps) <= 6
    error = jnp.abs(solution.value - ROOT)
    moved = jnp.abs(inverse) @ jnp.full(3, ATOL)
    assert float(error[0]) > 50 * ATOL  # a stall, far from the plain test
    assert bool(jnp.all(error <= STALL_FACTOR * moved))


def test_a_floor_far_above_the_tolerance_still_fails(route):
    solution = _solve(_floor_residual(STALL_FACTOR * ATOL), jnp.eye(3), route=route)
    assert solution.result != optx.RESULTS.successful


def test_slow_convergence_is_accepted_only_near_the_root(route):
    """A poor inverse (contraction c = 0.8) is accepted by the stall test once the
    correction is below STALL_FACTOR tolerances, and the iterate is then within
    STALL_FACTOR * c / (1 - c) tolerances of the root."""
    contraction = 0.8
    solution = _solve(lambda u, args: u - ROOT, (1 - contraction) * jnp.eye(3), max_steps=200, route=route)
    assert solution.result == optx.RESULTS.successful
    error = float(jnp.max(jnp.abs(solution.value - ROOT)))
    assert error <= STALL_FACTOR * contraction / (1 - contraction) * ATOL
    assert error > ATOL  # accepted by the stall test, not the plain one


def test_a_remainder_bound_iterates_until_the_estimated_error_is_below_it():
    """Contraction c = 0.05 (corrections shrink 20-fold, so the stall test never
    fires): without a bound the iteration stops at the first correction below the
    tolerance, leaving an error of up to c tolerances; with `remainder` it goes on
    until c |correction| is below `remainder` tolerances, and the error left is below
    that. An exact guess (zero corrections) still converges."""
    contraction, remainder = 0.05, 1e-4
    inverse = (1 - contraction) * jnp.eye(3)
    solve = PresetChord(atol=ATOL).solve
    plain = solve(lambda u, args: u - ROOT, jnp.zeros(3), None, inverse, 50)
    bounded = solve(lambda u, args: u - ROOT, jnp.zeros(3), None, inverse, 50, remainder=remainder)
    assert plain.result == bounded.result == optx.RESULTS.successful
    plain_error, bounded_error = (float(jnp.max(jnp.abs(s.value - ROOT))) for s in (plain, bounded))
    assert plain_error > remainder * ATOL
    assert bounded_error <= remainder * ATOL / (1 - contraction)
    assert int(bounded.steps) > int(plain.steps)
    exact = solve(lambda u, args: u - ROOT, ROOT, None, inverse, 50, remainder=remainder)
    assert exact.result == optx.RESULTS.successful and int(exact.steps) == 2


def test_a_remainder_bound_reads_the_contraction_before_a_correction_at_the_rounding_floor():
    """Contraction c = 0.01 from an error of 2e10 tolerances, with a rounding error of
    0.003 tolerances in the residual (`_floor_residual`): the corrections are about
    2e10, 2e8, ..., 2, then 0.02 (the seventh, c = 0.01 of it still left, so the error
    left 2e-4 tolerances is above the bound), then the eighth, at the floor, about 0.005.
    Its ratio to the seventh measures the rounding (0.25), but the two before it show
    the contraction, 0.01, and an error left of 5e-5 tolerances: the iteration stops
    there, where the ratio of the last two alone would have needed a ninth correction
    to see the stall. The error left is within the floor."""
    contraction, floor = 0.01, 0.003 * ATOL
    solution = PresetChord(atol=ATOL).solve(
        _floor_residual(floor), jnp.zeros(3), None, (1 - contraction) * jnp.eye(3), 50, remainder=1e-4
    )
    assert solution.result == optx.RESULTS.successful
    assert int(solution.steps) == 8
    np.testing.assert_allclose(solution.value, ROOT, rtol=0, atol=floor * (1 + 1e-6))


def test_a_relative_tolerance_may_be_traced_and_loosens_the_correction_test():
    """rtol given as a traced value (inside `jax.jit`) enters the tolerance of the
    corrections, atol + rtol |u|, as the same rtol given as a number does; the residual
    is still held to atol. Here the correction is 9 times the residual (residual
    0.1 (u - root), inverse 9 I, contraction 0.1), so with rtol |u| far above atol the
    correction test stops binding and the iteration ends sooner."""
    root = jnp.array([1e6, -2e6, 5e5])
    fn = lambda u, args: 0.1 * (u - root)  # noqa: E731
    inverse = 9.0 * jnp.eye(3)

    @jax.jit
    def traced(rtol):
        return PresetChord(atol=ATOL, rtol=rtol).solve(fn, jnp.zeros(3), None, inverse, 50)

    relative = traced(jnp.asarray(1e-6))
    number = PresetChord(atol=ATOL, rtol=1e-6).solve(fn, jnp.zeros(3), None, inverse, 50)
    absolute = PresetChord(atol=ATOL).solve(fn, jnp.zeros(3), None, inverse, 50)
    for solution in (relative, number, absolute):
        assert solution.result == optx.RESULTS.successful
        assert float(jnp.max(jnp.abs(fn(solution.value, None)))) < ATOL
    np.testing.assert_array_equal(relative.value, number.value)
    assert int(relative.steps) == int(number.steps) < int(absolute.steps)


@pytest.mark.parametrize("growth", [4.0, jnp.inf])
def test_growing_or_nonfinite_corrections_are_divergence(growth, route):
    solution = _solve(lambda u, args: growth * (u - ROOT) + 1.0, jnp.eye(3), route=route)
    assert solution.result == optx.RESULTS.nonlinear_divergence
    assert bool(jnp.all(jnp.isfinite(solution.value)))  # the last finite iterate


def test_too_few_iterations_and_a_nonfinite_start_are_reported(route):
    slow = _solve(lambda u, args: u - ROOT, 0.5 * jnp.eye(3), max_steps=5, route=route)
    assert slow.result == optx.RESULTS.nonlinear_max_steps_reached
    assert int(slow.steps) == 5
    nan_start = _solve(lambda u, args: u - ROOT, jnp.eye(3), route=route, y0=jnp.full(3, jnp.nan))
    assert nan_start.result == optx.RESULTS.nonfinite


_CASES = {
    "converging": (lambda u, args: u - ROOT + 0.05 * jnp.sin(u - ROOT), jnp.eye(3), 30),
    "stalling": (_floor_residual(1.5 * ATOL), jnp.eye(3), 30),
    "slow": (lambda u, args: u - ROOT, 0.2 * jnp.eye(3), 200),
    "too slow": (lambda u, args: u - ROOT, 0.5 * jnp.eye(3), 5),
    "diverging": (lambda u, args: 4.0 * (u - ROOT) + 1.0, jnp.eye(3), 30),
    "nan residual": (lambda u, args: jnp.where(u[0] > 0.1, jnp.nan, 1.0) * (u - ROOT), jnp.eye(3), 30),
}


@pytest.mark.parametrize("case", list(_CASES))
def test_own_loop_is_the_optimistix_iteration(case):
    """The same iterates, codes, counts and last residual size, to the bit, by both
    routes (jitted, as the methods run them)."""
    fn, inverse, max_steps = _CASES[case]
    own = jax.jit(lambda: _solve(fn, inverse, max_steps, "own loop"))()
    reference = jax.jit(lambda: _solve(fn, inverse, max_steps, "optimistix"))()
    for field in ("value", "steps", "residual_size"):
        np.testing.assert_array_equal(getattr(own, field), getattr(reference, field), err_msg=field)
    assert own.result == reference.result


@pytest.mark.parametrize("fixed_trip", [3, 1000])
@pytest.mark.parametrize("case", list(_CASES))
def test_a_fixed_trip_count_first_is_the_while_loop(case, fixed_trip):
    """`fixed_trip=k` runs the first k iterations (at most `max_steps`) in a loop of
    known trip count, those after the end masked, then the while loop: the same
    iterate, code, count and last residual size, to the bit, as the while loop alone."""
    fn, inverse, max_steps = _CASES[case]

    def solve(fixed_trip):
        chord = PresetChord(atol=ATOL, fixed_trip=fixed_trip)
        return chord.solve(fn, jnp.zeros(3), None, inverse, max_steps, remainder=1e-4)

    fixed, reference = (jax.jit(lambda k=k: solve(k)) for k in (fixed_trip, 0))
    for field in ("value", "steps", "residual_size"):
        np.testing.assert_array_equal(getattr(fixed(), field), getattr(reference(), field), err_msg=field)
    assert fixed().result == reference().result
    trips = min(fixed_trip, max_steps)
    assert f'"known_trip_count":{{"n":"{trips}"}}' in fixed.lower().compile().as_text()


def test_own_loop_under_vmap_gives_each_member_its_own_iteration():
    """A batch of starts that converge in different numbers of iterations, one of them
    NaN: each member's root, code and count are those of its own run alone."""
    fn, inverse = (lambda u, args: u - ROOT + 0.3 * jnp.sin(u - ROOT)), jnp.eye(3)
    starts = jnp.stack([ROOT + 1e-6, jnp.zeros(3), jnp.full(3, jnp.nan), ROOT - 3.0])
    batch = jax.jit(jax.vmap(lambda y0: _solve(fn, inverse, y0=y0)))(starts)
    assert len(set(np.asarray(batch.steps).tolist())) > 2
    for i, y0 in enumerate(starts):
        alone = _solve(fn, inverse, y0=y0)
        np.testing.assert_array_equal(batch.value[i], alone.value)
        assert int(batch.steps[i]) == int(alone.steps)
        assert int(batch.result._value[i]) == int(alone.result._value)
    assert int(batch.result._value[2]) == int(optx.RESULTS.nonfinite._value)


def test_chord_inverse_pivots_only_where_needed_also_within_a_batch():
    """A dominant matrix and one whose first pivot is zero, alone and in one vmapped
    batch: each gets its exact inverse (the second only by pivoting)."""
    dominant = jnp.array([[1.0, 0.2, -0.1], [0.3, -1.0, 0.2], [0.0, 0.4, 1.0]])
    needs_pivoting = jnp.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    jitted = jax.jit(chord_inverse)
    for a in (dominant, needs_pivoting):
        np.testing.assert_allclose(jitted(a) @ a, jnp.eye(3), atol=1e-15)
    batch = jax.jit(jax.vmap(chord_inverse))(jnp.stack([dominant, needs_pivoting, dominant]))
    for a, inverse_of_a in zip((dominant, needs_pivoting, dominant), batch):
        np.testing.assert_allclose(inverse_of_a @ a, jnp.eye(3), atol=1e-15)


def test_chord_inverse_keeps_an_accurate_unpivoted_inverse_and_pivots_an_inaccurate_one():
    """A matrix neither row- nor column-dominant but with pivots far from zero keeps
    its unpivoted inverse (bit for bit); one whose first pivot is tiny, whose
    unpivoted inverse is finite but wrong, gets the pivoted one; alone and in one
    vmapped batch."""
    moderate = jnp.array([[1.0, 0.9, 0.8, 0.1], [0.7, 1.0, 0.9, 0.3], [0.2, 0.8, 1.0, 0.9], [0.9, 0.1, 0.7, 1.0]])
    tiny_pivot = jnp.array([[1e-17, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]])
    assert not bool(is_diagonally_dominant(moderate))
    unpivoted = jax.jit(lambda a: inverse(a, pivoting=False))
    wrong = unpivoted(tiny_pivot)
    assert bool(jnp.all(jnp.isfinite(wrong))) and float(jnp.max(jnp.abs(wrong @ tiny_pivot - jnp.eye(3)))) > 0.1
    jitted = jax.jit(chord_inverse)
    np.testing.assert_array_equal(jitted(moderate), unpivoted(moderate))
    np.testing.assert_allclose(jitted(moderate) @ moderate, jnp.eye(4), atol=1e-14)
    np.testing.assert_allclose(jitted(tiny_pivot) @ tiny_pivot, jnp.eye(3), atol=1e-15)
    padded = jnp.zeros((4, 4)).at[:3, :3].set(tiny_pivot).at[3, 3].set(1.0)
    matrices = jnp.stack([moderate, padded, moderate])
    batch = jax.jit(jax.vmap(chord_inverse))(matrices)
    np.testing.assert_array_equal(batch[0], jax.jit(jax.vmap(unpivoted))(matrices)[0])
    for a, inverse_of_a in zip(matrices, batch):
        np.testing.assert_allclose(inverse_of_a @ a, jnp.eye(4), atol=1e-14)


def test_a_kept_chord_matrix_is_inverted_by_a_pivoted_lu_of_few_kernels():
    """`kept=True`: the exact inverse of a dominant matrix and of ones that need
    pivoting, alone and in one vmapped batch, non-finite for a singular or NaN one;
    for an 8 x 8 matrix a program of fewer distinct kernels to compile than the
    unrolled elimination's."""
    dominant = jnp.array([[1.0, 0.2, -0.1], [0.3, -1.0, 0.2], [0.0, 0.4, 1.0]])
    needs_pivoting = jnp.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    tiny_pivot = jnp.array([[1e-17, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]])
    singular = jnp.array([[1.0, 2.0, 0.0], [2.0, 4.0, 0.0], [0.0, 0.0, 1.0]])
    kept = jax.jit(lambda a: chord_inverse(a, kept=True))
    for a in (dominant, needs_pivoting, tiny_pivot):
        np.testing.assert_allclose(kept(a) @ a, jnp.eye(3), atol=1e-15)
    assert not bool(jnp.all(jnp.isfinite(kept(singular))))
    matrices = jnp.stack([dominant, needs_pivoting, jnp.full((3, 3), jnp.nan), tiny_pivot])
    batch = jax.jit(jax.vmap(lambda a: chord_inverse(a, kept=True)))(matrices)
    for k in (0, 1, 3):
        np.testing.assert_allclose(batch[k] @ matrices[k], jnp.eye(3), atol=1e-15)
    assert not bool(jnp.any(jnp.isfinite(batch[2])))

    chord_matrix = jnp.eye(8) - 0.1 * jnp.cos(jnp.arange(64.0)).reshape(8, 8)
    sizes = {
        kept_matrix: hlo_counts(jax.jit(lambda a: chord_inverse(a, kept=kept_matrix)).lower(chord_matrix).compile())
        for kept_matrix in (False, True)
    }
    assert sizes[True]["distinct_fusions"] < sizes[False]["distinct_fusions"] / 2, sizes


def test_a_failed_trajectorys_matrix_makes_no_batch_pivot(monkeypatch):
    """Under `vmap` a rare branch runs for the whole batch when one member takes it. A
    failed trajectory's NaN chord matrix gets a NaN inverse and makes no step of its
    batch run the pivoted inverse, where the batch's other matrices are checked and
    kept unpivoted; a member that needs pivoting still gets it beside a NaN one."""
    pivoted = []
    original = chord._pivoted_inverse

    def counted(operands):
        jax.debug.callback(lambda: pivoted.append(1))
        return original(operands)

    monkeypatch.setattr(chord, "_pivoted_inverse", counted)
    moderate = jnp.array([[1.0, 0.9, 0.8], [0.7, 1.0, 0.9], [0.2, 0.8, 1.0]])
    tiny_pivot = jnp.array([[1e-17, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]])
    failed = jnp.full((3, 3), jnp.nan)
    assert not bool(is_diagonally_dominant(moderate))
    batch = jax.jit(jax.vmap(chord_inverse))(jnp.stack([moderate, failed]))
    assert not pivoted
    np.testing.assert_allclose(batch[0] @ moderate, jnp.eye(3), atol=1e-14)
    assert not bool(jnp.any(jnp.isfinite(batch[1])))
    batch = jax.jit(jax.vmap(chord_inverse))(jnp.stack([tiny_pivot, failed]))
    assert pivoted
    np.testing.assert_allclose(batch[0] @ tiny_pivot, jnp.eye(3), atol=1e-15)
    assert not bool(jnp.any(jnp.isfinite(batch[1])))


def _computations(hlo: str) -> dict[str, list[str]]:
    computations, current = {}, None
    for line in hlo.splitlines():
        header = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{$", line)
        if header and "(" in line:
            current = computations.setdefault(header.group(1), [])
        elif line.startswith("}"):
            current = None
        elif current is not None and " = " in line:
            current.append(line)
    return computations


def _called(line: str) -> list[str]:
    names = re.findall(r"(?:body|condition|true_computation|false_computation|to_apply)=%?([\w.\-]+)", line)
    branches = re.search(r"branch_computations=\{([^}]*)\}", line)
    return names + ([name.strip().lstrip("%") for name in branches.group(1).split(",")] if branches else [])


_ITEM_BYTES = {"f64": 8, "f32": 4, "s64": 8, "s32": 4, "pred": 1}


def _array_bytes(shape: str) -> int:
    kind, dims = re.match(r"(\w+)\[([\d,]*)\]", shape).groups()
    return int(np.prod([int(d) for d in dims.split(",") if d])) * _ITEM_BYTES[kind]


_NOT_RUN = ("parameter", "get-tuple-element", "tuple", "constant", "bitcast", "while", "conditional", "call")


def _largest_array(computations, name, seen=()) -> int:
    """The largest array (bytes) an operation of computation `name` or of one it calls
    (loop bodies, branches) reads or writes, as XLA:CPU counts it for its choice to run
    them one after another (fused computations count by their operands and result)."""
    shapes, largest = {}, 0
    for line in computations.get(name, []):
        match = re.match(r"\s*(?:ROOT )?%?([\w.\-]+) = (\(.*?\)|\S+) ([\w\-]+)\((.*?)\)", line)
        if not match:
            continue
        result, shape, op, operands = match.groups()
        shapes[result] = shape
        if op not in _NOT_RUN:
            for s in [shape] + [shapes.get(o.strip().lstrip("%"), "") for o in operands.split(",")]:
                if re.match(r"(f64|f32|s64|s32|pred)\[", s):  # not tuples
                    largest = max(largest, _array_bytes(s))
        if op in ("while", "conditional"):
            for child in _called(line):
                if child not in seen:
                    largest = max(largest, _largest_array(computations, child, seen + (name,)))
    return largest


def _loops(computations) -> list[str]:
    return [child for lines in computations.values() for line in lines if " while(" in line
            for child in re.findall(r"body=%?([\w.\-]+)", line)]


@pytest.mark.parametrize(
    "case, method", [("disk", nh.GonzalezR()), ("gearbox", nh.EnergyPreservingCollocation(order=4))], ids=str
)
def test_chord_iterations_touch_only_arrays_xla_runs_in_sequence(case, method):
    """XLA:CPU runs a loop body's operations one after another only where no array they
    touch exceeds `SEQUENTIAL_BYTES` (otherwise on its thread pool, which costs more
    than tiny operations): in no loop of a run, the steps and the chord iterations,
    does any. Euler's disk needs `solve_spd`'s batch of right-hand sides folded into
    columns (three 5 x 6 eliminations batched are 720 bytes), and in the steps' loop
    its kept exact chord matrix formed a column at a time (`GonzalezR._columnwise`);
    the gearbox's collocation of order 4, with 10 unknowns, its inverse formed and read
    in blocks of rows (`EnergyPreservingCollocation.chord_matrix`)."""
    if case == "disk":
        disk = nh.examples.rolling_disk_3d()
        y0 = disk.state(q=jnp.array([0.3, -0.2, 0.4, 0.25, 0.1]), turn_rate=0.6, lean_rate=-0.3, spin_rate=2.5)
        system, args, h = disk.canonical, disk.args, 0.01
    else:
        gearbox = nh.examples.gearbox()
        system, y0, args, h = gearbox.canonical, gearbox.random_initial_state(jax.random.key(0)), None, 0.1
    run = jax.jit(lambda y: nh.integrate(system, method, y, h, 3, args=args))
    computations = _computations(run.lower(y0).compile().as_text())
    loops = _loops(computations)
    assert len(loops) >= 2
    sizes = {loop: _largest_array(computations, loop) for loop in loops}
    assert max(sizes.values()) <= SEQUENTIAL_BYTES, sizes


def _contains_loop(computations, name, seen=()) -> bool:
    for line in computations.get(name, []):
        if " while(" in line:
            return True
        if any(_contains_loop(computations, child, seen + (name,)) for child in _called(line) if child not in seen):
            return True
    return False


def test_the_discrete_gradients_chord_iterations_touch_only_arrays_xla_runs_in_sequence():
    """DiscreteGradient on the quartic's adapted form ($N = 13$): its structure matrix,
    1 352 bytes, is formed in the chord iteration's residual but is not an array of the
    iteration's loop, since the residual's product with it is fused
    (`DiscreteGradient._equations`); the loop of the steps, which forms the chord matrix,
    keeps it. Every loop with none inside it (the iterations') runs in sequence."""
    quartic = nh.examples.chaotic_quartic(3)
    run = jax.jit(lambda x: nh.integrate(quartic.adapted, nh.DiscreteGradient(), x, 0.1, 3))
    computations = _computations(run.lower(quartic.initial_state(0.7)).compile().as_text())
    loops = _loops(computations)
    innermost = [loop for loop in loops if not _contains_loop(computations, loop)]
    outer = [loop for loop in loops if loop not in innermost]
    assert innermost and outer
    assert max(_largest_array(computations, loop) for loop in outer) > SEQUENTIAL_BYTES
    sizes = {loop: _largest_array(computations, loop) for loop in innermost}
    assert max(sizes.values()) <= SEQUENTIAL_BYTES, sizes
