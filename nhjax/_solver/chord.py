r"""A chord root finder that takes its Jacobian approximation from the method.

A discrete-gradient step solves $F(u) = u - (h/s)\,\Pi(\bar\zeta)\,\bar\nabla\mathcal{H} = 0$.
The exact Jacobian contains the derivative of the discrete gradient's correction term,
which is $O(|\delta|^2)$ and needs higher derivatives of $\mathcal{H}$ (through a
QR factorisation, for GONZALEZ-R). Dropping it changes $\partial\bar\nabla\mathcal{H}$
by $O(|\delta|)$ and the Jacobian of $F$ by $O(h|\delta|) = O(h^2)$ (fitted 2.0 on
the quartic, `tests/test_solver/test_discrete_gradient.py`), as freezing it at the
predictor does, so the chord iteration $u \leftarrow u - \tilde J^{-1}F(u)$ still
contracts by a factor $O(h^2)$ per iteration, at a fraction of the cost of Newton's
method. The converged root is the same
(to the tolerance), and derivatives of the root with respect to the inputs come from
the implicit function theorem with the exact Jacobian of $F$
(`nhjax._solver.base._implicit_root`), so they are exact too. (GONZALEZ-R's matrix
holds the frame fixed to first order, an $O(h)$ change that costs a few iterations and
saves $O(n^2k^2)$ work per step: `nhjax.GonzalezR.chord_jacobian`; it then bounds the
error the iteration leaves, `PresetChord.solve`'s `remainder`.)
"""

import functools
from typing import Any

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float, Int, Scalar

from .._linalg import (
    blocked_product,
    inverse,
    is_accurate_inverse,
    is_diagonally_dominant,
    lapack_inverse,
    product,
    row_blocks,
    UNROLL_LIMIT,
)
from .._rare_branch import rarely


STALL_FACTOR = 8.0
# The error a slowly contracting iteration may leave, in units of its tolerance, where
# the method asks for a bound (`PresetChord.solve`): 1e-4 of 64 eps, below the rounding.
REMAINDER = 1e-4


def chord_inverse(jacobian: Float[Array, "n n"], kept: bool = False) -> Float[Array, "n n"]:
    r"""The inverse of a chord matrix (`nhjax._linalg`): by elimination without pivoting
    wherever that is accurate, with partial pivoting elsewhere.

    Elimination without pivoting is stable for a diagonally dominant matrix, as
    $I - O(h)$ is for small steps and the methods whose unknowns are increments. At
    large steps a chord matrix is often not dominant yet well conditioned, with
    pivots far from zero (the energy-preserving collocation's real blocks at order
    12 and $h = 0.7$ on the quartic, of condition 1.6 to 2.8): there the unpivoted
    inverse $X$ is kept where $\max|JX - I| \le \sqrt\varepsilon$
    (`nhjax._linalg.is_accurate_inverse`), an error that changes the iteration's
    contraction by as little, not its root; a vanishing or tiny pivot fails that
    test, and LAPACK's pivoted LU runs (`nhjax._linalg.lapack_inverse`: a few
    instructions in the program where the unrolled pivoted elimination was some 600
    at $n = 8$; `benchmarks/composition.py` measures the collocation's steps).
    GONZALEZ-F's multiplier block has a zero diagonal, but it is eliminated last,
    after it has filled in: on the gearbox, the sleigh and Euler's disk its matrices
    pass the test unpivoted.
    Under `vmap` the test and the pivoted LU
    run only at the steps where some trajectory needs them (`rarely`), never for a
    non-finite matrix (a failed trajectory's). Cut from differentiation, as the chord
    matrix is.

    `kept`: a matrix kept from step to step (`AbstractMethod.reuses_chord_matrix`),
    formed at a few steps only, is inverted by LAPACK's pivoted LU whatever it is. Its
    library call costs little at those steps, and it is a few instructions in the
    program where the unrolled elimination is $n$ eliminations of a column, each a
    kernel of its own for XLA to compile (`benchmarks/_profile.hlo_counts`'s
    `distinct_fusions`): Euler's disk's GONZALEZ-R run of 2 000 steps ($N = 8$, the
    matrix formed at 126 of them) holds 344 distinct fused computations against 378,
    with the same iterations and states (`python benchmarks/gradients.py --systems disk
    --parts` measures its compilation and steps)."""
    jacobian = lax.stop_gradient(jacobian)
    if kept:
        return lapack_inverse(jacobian)
    if jacobian.shape[0] > UNROLL_LIMIT:
        return inverse(jacobian)
    unpivoted = inverse(jacobian, pivoting=False)
    # A non-finite matrix has no better inverse than the unpivoted one, non-finite too:
    # a failed trajectory's, in a batch, would otherwise make every step of the batch
    # take both branches.
    checked = ~is_diagonally_dominant(jacobian) & jnp.all(jnp.isfinite(jacobian))
    return rarely(checked, _checked_inverse, unpivoted, (jacobian, unpivoted, checked))


def _checked_inverse(operands):
    """The unpivoted inverse where it is accurate, else the pivoted one. Under `vmap`
    this branch runs for the whole batch, so the test is taken only where the matrix
    was to be checked (`checked`): a failed trajectory's NaN inverse is not accurate
    either."""
    jacobian, unpivoted, checked = operands
    return rarely(checked & ~is_accurate_inverse(jacobian, unpivoted), _pivoted_inverse, unpivoted, operands)


def _pivoted_inverse(operands):
    return lapack_inverse(operands[0])


class _ChordState(eqx.Module):
    # In blocks of rows (`row_blocks`) small enough that a loop's operations around
    # them run one after another (`nhjax._linalg.SEQUENTIAL_BYTES`).
    inverse: tuple[Float[Array, "r n"], ...]
    floor: Float[Array, " n"]
    correction_floor: Float[Array, " n"]
    # How many of its units a stalled correction may take (`terminate`).
    stall_allowance: Float[Array, ""]
    # The sizes of the last correction and of the one before it, the ratio of the two
    # before the last, and the size of the last residual, in one array: it is formed
    # anew at each iteration, where separate scalars moved from one slot of the loop's
    # carry to another cost XLA a copy each per iteration.
    sizes: Float[Array, "4"]
    steps: Int[Array, ""]

    @property
    def diff_size(self):
        return self.sizes[0]

    @property
    def previous_diff_size(self):
        return self.sizes[1]

    @property
    def previous_contraction(self):
        return self.sizes[2]

    @property
    def residual_size(self):
        return self.sizes[3]


class ChordSolution(eqx.Module):
    """The end of a root find: the last iterate, the optimistix code, the iterations
    taken, and the size of the last residual evaluated, non-finite where the function
    returned NaN or inf (from `PresetChord.solve` in units of `atol`; the methods read
    only whether it is finite, and give other root finders' results this form too)."""

    value: Float[Array, " n"]
    result: optx.RESULTS
    steps: Int[Array, ""]
    residual_size: Scalar


class PresetChord(optx.AbstractRootFinder):
    r"""PresetChord iteration for a root of `fn(u, args)`, `u` a 1-D array.

    The inverse Jacobian approximation is `options["inverse"]` when the caller supplies
    one, as a matrix or as its blocks of rows (`nhjax._linalg.row_blocks`, or blocks a
    method forms as they are; formed explicitly, `chord_inverse`: one matrix-vector product per
    iteration instead of two triangular solves; the chord matrix is well conditioned,
    $I - O(h)$, and the inverse's rounding changes the contraction rate, not the root);
    otherwise the inverse of
    `options["jacobian"]`, or of `jax.jacfwd(fn)` at the initial guess. Stops when
    the last correction and the residual are both below `atol` (max norm), or when the
    iteration has stalled at the rounding floor (below); fails with
    `optimistix.RESULTS.nonlinear_divergence` if the corrections grow (by more than 2x
    from one iteration to the next) or become non-finite, then returning the last
    finite iterate. The state's `residual_size` is that of the last residual evaluated
    (in units of `atol`): non-finite when the function returned NaN or inf there.

    **Stall at the rounding floor.** A residual that involves a discrete gradient is
    computed with an error of about $\varepsilon|H|/|x' - x|$ (the difference
    $H(x') - H(x)$ divided by the increment), which for large states comes within a few
    `atol` of the tolerance. The iterates then circle the root (the corrections flip
    sign without shrinking) and the plain test may never pass, or pass only on some
    rounding paths. So an iteration is also accepted once, from the second correction
    on, the correction and the residual are both below `STALL_FACTOR` of their units
    (those of the test below) and the correction is no longer halving: the root is then
    known to a few tolerances, which is all the rounding allows. (With a contraction
    rate $c$, a slowly converging iteration accepted this way is within `STALL_FACTOR`
    $c/(1 - c)$ tolerances of its root; for the nhjax methods $c = O(h^2)$, see the
    module docstring.) Where the chord matrix is ill-conditioned the rounding of the
    residual comes back amplified in the correction, which then stalls at many of its
    units while the residual stalls at a few: GONZALEZ-F on a tractor pulling 61
    trailers, whose constraint rows stall at 2 to 4 tolerances and whose chord matrix,
    of condition 740, turns them into corrections of 10 to 20. So the correction's
    bound is `STALL_FACTOR` times the largest factor, over the components, by which
    $|\tilde J^{-1}|$ turns a residual at its units into a correction beyond the
    correction's units ($\max_i\,(|\tilde J^{-1}|(\text{atol} + \text{floor}))_i
    / (\text{atol} + |\tilde J^{-1}|\,\text{floor})_i$, at least 1; $1 + O(h)$ for a
    chord matrix $I - O(h)$). It is the residual's bound that bounds the error:
    $|u - u^*| \lesssim |\tilde J^{-1}|\,|F(u)|$, within `STALL_FACTOR` such
    corrections, component by component.

    **A floor the caller knows.** Where the residual's rounding is known to exceed
    `atol` in some components, `options["floor"]` (a vector, default zero) gives its
    size there: the residual is then measured in units of `atol + floor` per
    component, and the correction in units of `atol + |inverse| floor`, the correction
    that a residual at its floor causes. The methods pass the rounding of the points
    at which their residuals evaluate the system (`nhjax.AbstractMethod.resolution`):
    an angle wound up to $10^6$ is known to $10^{-10}$, and a force that depends on it
    only to $10^{-10}$ times its derivative, whatever the tolerance asks. The
    projection (`nhjax.Projection`) passes the rounding of the invariants, which near
    an equilibrium, where their gradients are small, moves the state by more than
    `atol` per iteration.

    **A fixed trip count first** (`fixed_trip=k`; `solve` only): the first k iterations
    run in a loop of a trip count fixed at compile time, those after the iteration has
    stopped masked (they keep the carry), and a while loop takes the rest, up to
    `max_steps`: the same iterate, code and count as the while loop alone. On a GPU the
    condition of a while loop is copied to the host at every iteration; with k at least
    the usual number of iterations, a step copies it once, at the price of the masked
    iterations (`benchmarks/gpu.py` measures it).
    """

    atol: float
    rtol: float = 0.0
    norm: Any = optx.max_norm
    fixed_trip: int = 0

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del f_struct, aux_struct, tags
        inverse = options.get("inverse")
        if inverse is None:
            jacobian = options.get("jacobian")
            if jacobian is None:
                jacobian = jax.jacfwd(lambda u: fn(u, args)[0])(y)
            inverse = chord_inverse(jacobian)
        inverse = lax.stop_gradient(inverse)
        floor = options.get("floor")
        floor = jnp.zeros_like(y) if floor is None else lax.stop_gradient(jnp.broadcast_to(floor, y.shape))
        # What a residual at its floor moves the iterate by: corrections of that size
        # are rounding, not progress; and what one at its tolerance and floor moves it
        # by, against the correction's units, for the stall test. Of a whole matrix in
        # one product: its blocks of rows are slices, each an operation of its own.
        def moved(block):
            magnitude = jnp.abs(block)
            return product(magnitude, floor), jnp.sum(magnitude, axis=1)

        if isinstance(inverse, tuple):
            blocks = inverse
            correction_floor, row_sums = (jnp.concatenate(parts) for parts in zip(*map(moved, blocks)))
        else:
            blocks, (correction_floor, row_sums) = row_blocks(inverse), moved(inverse)
        stall_allowance = jnp.maximum(
            1.0, jnp.max((self.atol * row_sums + correction_floor) / (self.atol + correction_floor))
        )
        return _ChordState(
            blocks, floor, correction_floor, stall_allowance, jnp.full(4, jnp.inf, dtype=y.dtype), jnp.array(0)
        )

    def step(self, fn, y, args, options, state, tags):
        del options, tags
        residual, aux = fn(y, args)
        diff = blocked_product(state.inverse, residual)
        # A relative tolerance given as the number 0 adds nothing: the iterate's norm
        # is then not computed (0 * norm still costs a reduction on XLA). A traced or
        # array rtol keeps the general form.
        no_rtol = isinstance(self.rtol, (int, float)) and self.rtol == 0
        tolerance = self.atol if no_rtol else self.atol + self.rtol * self.norm(y)
        diff_size = self.norm(diff / (tolerance + state.correction_floor))
        # A non-finite correction (a NaN residual, a singular matrix) ends the
        # iteration as diverged; the iterate stays the last finite one, so that the
        # caller can still tell where the step was heading. The norm is non-finite
        # exactly when the correction is (norms propagate NaN and inf), so one reduction
        # serves both.
        finite = jnp.isfinite(diff_size)
        new_state = _ChordState(
            state.inverse,
            state.floor,
            state.correction_floor,
            state.stall_allowance,
            jnp.stack([
                jnp.where(finite, diff_size, jnp.nan),
                state.diff_size,
                state.diff_size / state.previous_diff_size,
                self.norm(residual / (self.atol + state.floor)),
            ]),
            state.steps + 1,
        )
        return jnp.where(finite, y - diff, y), new_state, aux

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, tags
        converged = (state.diff_size < 1) & (state.residual_size < 1)
        remainder = (options or {}).get("remainder")
        if remainder is not None:
            # The error left after the last correction, estimated as theta |diff| with
            # the contraction theta = |diff| / |previous diff| (as Hairer and Wanner,
            # Solving ODEs II, §IV.8, estimate it for simplified Newton iterations).
            # A chord iteration contracts at its matrix's rate at every iterate, but a
            # correction at the rounding floor measures the rounding: there the ratio
            # of the two corrections before it is the better estimate, and the smaller
            # of the two ratios is taken (from the third correction on).
            left = (state.diff_size * state.diff_size <= remainder * state.previous_diff_size) | (
                (state.steps >= 3)
                & (state.diff_size <= state.previous_diff_size)
                & (state.diff_size * state.previous_contraction <= remainder)
            )
            converged = converged & (state.steps >= 2) & left
        stalled = (
            (state.steps >= 2)
            & (state.diff_size < STALL_FACTOR * state.stall_allowance)
            & (state.residual_size < STALL_FACTOR)
            & (state.diff_size > 0.5 * state.previous_diff_size)
        )
        converged = converged | stalled
        started = state.steps >= 1
        diverged = started & (
            ~jnp.isfinite(state.diff_size)
            | ((state.steps >= 2) & (state.diff_size > 2 * state.previous_diff_size))
        )
        result = optx.RESULTS.where(
            diverged & ~converged, optx.RESULTS.nonlinear_divergence, optx.RESULTS.successful
        )
        return converged | diverged, result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, args, options, state, tags, result
        return y, aux, {}

    def solve(
        self,
        fn,
        y0: Float[Array, " n"],
        args,
        inverse: Float[Array, "n n"] | tuple[Float[Array, "r n"], ...],
        max_steps: int,
        floor: Float[Array, " n"] | None = None,
        remainder: float | None = None,
    ) -> ChordSolution:
        """The iteration for a root of `fn(u, args)` (no auxiliary output) from `y0`
        with the inverse Jacobian approximation `inverse` (a matrix or its blocks of
        rows): the iterates, codes and
        counts of `optimistix.root_find(fn, self, y0, args, options=dict(inverse=...),
        max_steps=max_steps, throw=False)`, including
        `optimistix.RESULTS.nonlinear_max_steps_reached` and `nonfinite` for a
        non-finite iterate, computed by a plain `lax.while_loop`; `floor` as
        `options["floor"]` (see the class docstring).

        `remainder` (`None`: no bound): for an inverse that contracts the iteration
        only slowly, also continue until the error the returned iterate keeps,
        estimated from the contraction of the last two corrections, is below
        `remainder` tolerances (`REMAINDER`: below the rounding), unless the iteration
        has stalled at the rounding floor. From the third correction on the contraction
        is also read from the two corrections before the last, and the smaller estimate
        taken: a last correction at the rounding floor measures the rounding, and
        without this the iteration often took one more correction to see the stall.
        An error below the tolerance but of one sign from step to step (the chord
        matrix's error is smooth along a trajectory) would otherwise add up: with a
        matrix contracting by 0.002 per iteration, the energy of the 3D rolling disk
        drifted by 2.6e-13 relative in 20 000 steps, against 1.6e-14 with the bound.

        The loop carries only what changes: the inverse and the floors, which do not,
        stay outside it. Under `vmap` a while loop's body ends with a select between the
        old and the new carry of every trajectory, and carrying the inverse (as
        optimistix's solver state does) would copy an n-by-n matrix per trajectory per
        iteration;
        `benchmarks/gonzalez_r.py` measures the batch. No derivatives flow through the
        loop: its inputs are constants, and the methods differentiate the root by the
        implicit function theorem."""
        fn_with_aux = lambda u, a: (fn(u, a), None)
        state = self.init(fn_with_aux, y0, args, dict(inverse=inverse, floor=floor), None, None, frozenset())
        constants = (state.inverse, state.floor, state.correction_floor, state.stall_allowance)

        def terminate_and_result(y, state):
            terminate, result = self.terminate(fn_with_aux, y, args, dict(remainder=remainder), state, frozenset())
            return terminate, optx.RESULTS.where(jnp.all(jnp.isfinite(y)), result, optx.RESULTS.nonfinite)

        def cond(carry):
            _, state, terminate, result = carry
            return ~terminate & (result == optx.RESULTS.successful) & (state.steps < max_steps)

        def body(carry):
            y, state, _, _ = carry
            new_y, new_state, _ = self.step(fn_with_aux, y, args, None, _with_constants(state, constants), frozenset())
            ended = terminate_and_result(y, new_state)
            return (new_y, _with_constants(new_state, (None, None, None, None))) + ended

        init = (y0, _with_constants(state, (None, None, None, None))) + terminate_and_result(y0, state)
        if self.fixed_trip:
            # Every one of these iterations runs; those after the end keep the carry.
            def masked_body(_, carry):
                return jax.tree.map(functools.partial(jnp.where, cond(carry)), body(carry), carry)

            init = lax.fori_loop(0, min(self.fixed_trip, max_steps), masked_body, init)
        y, state, terminate, result = lax.while_loop(cond, body, init)
        result = optx.RESULTS.where(
            (result == optx.RESULTS.successful) & ~terminate, optx.RESULTS.nonlinear_max_steps_reached, result
        )
        return ChordSolution(y, result, state.steps, state.residual_size)


def _with_constants(state: _ChordState, constants) -> _ChordState:
    """`state` with its constants (the inverse, the floors and the stall allowance)
    replaced."""
    return eqx.tree_at(
        lambda s: (s.inverse, s.floor, s.correction_floor, s.stall_allowance),
        state,
        constants,
        is_leaf=lambda x: x is None,
    )
