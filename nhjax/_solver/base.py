"""What every nhjax method shares: an optimistix root find per step, with tolerances
that follow the dtype, per-step result codes, and root-finder statistics carried in the
diffrax solver state.

diffrax's loop accepts only its own result codes from a step, so a step's failure
travels in the solver state as an `nhjax.RESULTS` code naming its cause
(`step_failure`), while the step reports `diffrax.RESULTS.breakdown`;
`nhjax.integrate` reports the nhjax code."""

import functools
from collections.abc import Callable
from typing import Any, ClassVar

import diffrax
import equinox as eqx
import jax
import jax.flatten_util
import jax.lax as lax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float, Int, PyTree, Scalar

from .._ledger import Ledgered, unledgered
from .._linalg import solve
from .._reduced import metric_is, metric_of
from .._rare_branch import rarely
from .._results import first_failure, from_diffrax, nan_where_failed, RESULTS
from .._system import AbstractSystem, is_int
from .._tangents import split_by_tangents
from .chord import chord_inverse, ChordSolution, PresetChord


def unwrapped_system(terms) -> AbstractSystem:
    """The user's system inside the wrappers diffrax puts around a term."""
    system = terms
    while not isinstance(system, AbstractSystem):
        system = system.term
    return system


def no_gradient(tree: PyTree) -> PyTree:
    """`tree` with its arrays cut from differentiation (`lax.stop_gradient`), its other
    leaves kept."""
    arrays, static = eqx.partition(tree, eqx.is_array)
    return eqx.combine(lax.stop_gradient(arrays), static)


@eqx.filter_custom_jvp
def _implicit_root(root, data, *, residual, replayed: bool = False):
    r"""`root`, a root of `residual(., data)`, with the derivatives the implicit function
    theorem gives it: $\dot u = -(\partial_u F)^{-1}\,\partial_{\text{data}}F\,
    \dot{\text{data}}$, with the exact Jacobian $\partial_u F$ at the root.

    This is what optimistix's `ImplicitAdjoint` computes, done here because its lineax
    solve raises a runtime error when it meets a non-finite value, and under `vmap` one
    failed trajectory (whose states are NaN from the failure on) would then stop the
    derivatives of the whole batch. Here a failed trajectory's derivatives are NaN and
    its neighbours' are unaffected.

    `replayed=True` (derivative programs only, `AbstractMethod.replay_step`): the value
    is `root` plus an exact zero whose derivative is NaN (`_nan_derivative`). The
    forward run keeps the bare `root`: an added zero would leave its values the same
    but could change how XLA fuses, and with it the rounding, of what follows."""
    del residual
    if replayed:
        return root + _nan_derivative(data).astype(root.dtype)
    return root


def _nan_derivative(data) -> Array:
    r"""Zero, whose derivative with respect to `data` is NaN: $\sqrt{0\cdot s}$ with $s$
    the sum of one element of each of the data's floating-point leaves (finite, so that
    the value is exactly zero whatever the data hold), whose derivative is
    $0\cdot\dot s/(2\sqrt0)$ = NaN.

    `_implicit_root`'s value is the root itself, a constant as a function of the data;
    differentiated, it would give a zero derivative, i.e. a wrong one. Autodiff reaches
    it only where JAX has dropped the derivative rule: its partial evaluation for
    reverse mode inlines a custom-JVP function's body inside a loop, and a second
    derivative with reverse mode inside (`jax.hessian`, `jax.jacfwd(jax.grad(f))`) then
    differentiates that body. Those second derivatives come out NaN, not wrong; forward
    mode inside (`jax.jacfwd(jax.jacfwd(f))`, `jax.jacrev(jax.jacfwd(f))`) keeps the rule
    and is exact."""
    firsts = [
        jnp.ravel(leaf)[0]
        for leaf in jax.tree.leaves(data)
        if eqx.is_inexact_array(leaf) and leaf.size > 0 and not jnp.issubdtype(leaf.dtype, jnp.complexfloating)
    ]
    if not firsts:
        return jnp.zeros(())
    total = sum(jnp.where(jnp.isfinite(x), x, jnp.zeros_like(x)) for x in firsts)
    return jnp.sqrt(0 * total)


@_implicit_root.def_jvp
def _implicit_root_jvp(primals, tangents, *, residual, replayed: bool = False):
    root, data = primals
    _, data_tangent = tangents
    # The root as a function of the data again, so that differentiating this rule (second
    # derivatives) sees the root, and with it the Jacobian below, move with the data.
    root = _implicit_root(root, data, residual=residual, replayed=replayed)
    _, jacobian, residual_tangent = _linearised(residual, root, data, data_tangent)
    return root, -solve(jacobian, residual_tangent)


# Up to this many differentiable entries in a step's data, `_linearised` forms the
# residual's derivative along each of them, as it does along the unknowns.
FORMED_DATA_DERIVATIVE_LIMIT = 32


def _linearised(equations, root, data, data_tangent):
    r"""`equations(root, data)` (a pytree whose first leaf is the residual), its
    derivative in the unknowns at `root`, formed (for each output leaf, the unknowns
    along its last axis), and its derivative along the data's tangent.

    Where the data have at most `FORMED_DATA_DERIVATIVE_LIMIT` differentiable entries
    (a state, a step size and a few parameters), the whole derivative of the
    equations' $M$ outputs in the $N$ unknowns and the $D$ data entries is formed, a
    row at a time: one pullback of the equations, applied to the $M$ unit vectors in
    one batch, where forming it a column at a time took $N + D$ tangents, and $D \ge
    N$ where the step's start varies (GONZALEZ-R's data: $\zeta$, $\mathcal{H}(\zeta)$
    and $p$, $D = N + n + 1$; `benchmarks/gradients.py --parts` times a step's
    derivative, `step_derivative`, and whole runs). The data's tangent enters by a
    matrix-vector product, which does not depend on the tangent, so in reverse mode
    the transpose of the step's derivative is that product's: transposing a
    linearisation would put a second copy of the residual's derivative (for
    GONZALEZ-R, second derivatives of the QR) into the program.

    With more entries (large systems, or a control signal in the data) the rows
    would be as long, and stored at every step of a run's derivative: the derivative
    in the unknowns is formed from one linearisation, a column at a time, and the
    one tangent along the data is taken from it."""
    varying, fixed, tangent_in = split_by_tangents(data, data_tangent)

    def on_varying(u, v):
        return equations(u, eqx.combine(v, fixed))

    if sum(leaf.size for leaf in jax.tree.leaves(varying)) <= FORMED_DATA_DERIVATIVE_LIMIT:
        # Pulled back to the data as one flat vector, so that each row comes out flat.
        flat_varying, unravel_varying = jax.flatten_util.ravel_pytree(varying)
        value, pullback = jax.vjp(lambda u, w: on_varying(u, unravel_varying(w)), root, flat_varying)
        flat_value, unravel_value = jax.flatten_util.ravel_pytree(value)
        along_unknowns, along_varying = jax.vmap(lambda e: pullback(unravel_value(e)))(
            jnp.eye(flat_value.size, dtype=flat_value.dtype)
        )
        flat_tangent = jax.flatten_util.ravel_pytree(tangent_in)[0]
        along_data = along_varying @ flat_tangent.astype(along_varying.dtype)
        # Each output leaf with the unknowns along its last axis.
        along_unknowns = jax.vmap(unravel_value, in_axes=1, out_axes=-1)(along_unknowns)
        return value, along_unknowns, unravel_value(along_data)
    value, linear = jax.linearize(on_varying, root, varying)
    n = root.shape[0]
    no_tangent = jax.tree.map(jnp.zeros_like, varying)
    unit = jnp.eye(n, dtype=root.dtype)
    along_unknowns = jax.vmap(lambda e: linear(e, no_tangent), out_axes=-1)(unit)
    return value, along_unknowns, linear(jnp.zeros_like(root), tangent_in)


@eqx.filter_custom_jvp
def _implicit_root_and_exchange(root, data, *, residual, equations, replayed: bool = False):
    r"""`_implicit_root`, and the step's exchange at it: `(root, exchange)` with
    `equations(u, data) = (residual(u, data), exchange(u, data))`
    (`AbstractMethod.residual_and_exchange`).

    The exchange's derivative $\dot E = \partial_uE\,\dot u + \partial_{\text{data}}E\,
    \dot{\text{data}}$ comes from the linearisation that gives the root's: a forced
    system's step is linearised once, not once for the root and again for its
    exchange, which made derivative programs of forced runs a fifth larger."""
    root = _implicit_root(root, data, residual=residual, replayed=replayed)
    return root, equations(root, data)[1]


@_implicit_root_and_exchange.def_jvp
def _implicit_root_and_exchange_jvp(primals, tangents, *, residual, equations, replayed: bool = False):
    root, data = primals
    _, data_tangent = tangents
    # As in `_implicit_root_jvp`; the exchange's value comes from the linearisation,
    # whose own derivatives (second derivatives) see the root move with the data.
    root = _implicit_root(root, data, residual=residual, replayed=replayed)
    (_, exchange), (jacobian, exchange_rows), (residual_tangent, exchange_tangent) = _linearised(
        equations, root, data, data_tangent
    )
    root_tangent = -solve(jacobian, residual_tangent)
    exchange_tangent = jax.tree.map(lambda along_data, row: along_data + row @ root_tangent, exchange_tangent, exchange_rows)
    return (root, exchange), (root_tangent, exchange_tangent)


class AbstractMethodState(eqx.Module):
    """What the loop reads from the diffrax solver state of an nhjax method after a run:
    `failure`, the nhjax code of the step that failed, if one did, and `statistics()`,
    the root-finder counts that `nhjax.Solution.stats` reports."""

    failure: eqx.AbstractVar[RESULTS]

    def statistics(self) -> dict[str, Array]:
        raise NotImplementedError


class AbstractCountingState(AbstractMethodState):
    """A solver state that counts root-finder (or projection) iterations: in all, and
    the most at one step."""

    total_steps: Int[Array, ""]
    max_steps: Int[Array, ""]

    def statistics(self) -> dict[str, Array]:
        """`root_find_steps`, iterations in all, and `max_root_find_steps`, the most in
        one step."""
        return dict(root_find_steps=self.total_steps, max_root_find_steps=self.max_steps)


# How closely a kept chord matrix's key must match the step's (relative): a step size
# t1 - t0 from accumulated times differs from the last one by rounding, and a matrix
# serves as well for it; the substeps of a composition differ by factors of order one.
CHORD_KEY_TOLERANCE = 1e-6
# A kept chord matrix serves at most this many steps: the same steps for every
# trajectory of a batch, so that under `vmap` the batch forms fresh matrices at steps
# where every trajectory takes one (`AbstractMethod.reuses_chord_matrix`). With
# GONZALEZ-R (`benchmarks/chord_reuse.py`) a batch of 32 Euler's disks then takes 0.89
# of the time of a fresh matrix at every step, where it took 1.06 to 1.17 when each
# trajectory replaced its matrix once its iterations grew by more than one, at steps of
# its own. The looser bound on the iterations (`_chord_solve`) costs where a matrix goes
# stale within a few steps: the gearbox took 1.47 with a kept matrix, 0.92 to 1.15 with
# the tighter one.
KEPT_STEPS = 16


# Above this many unknowns a fresh chord matrix (N tangents of the field, an N x N
# inverse) costs several iterations even where the metric is constant, and the methods
# that offer `reuse_chord_matrix` keep it by default: with the synthetic systems of
# `benchmarks/scaling.py`, keeping GONZALEZ-R's takes n = 64 (N = 112) 0.51 to 0.81 of
# the time from run to run, but n = 16 and 32 anything from 0.70 to 1.05.
KEPT_ABOVE_UNKNOWNS = 64


def chord_matrix_is_dear(system, y0, args, unknowns: Callable[[int, int], int]) -> bool:
    r"""Whether forming a chord matrix costs several iterations, so that the methods
    offering `reuse_chord_matrix` keep it by default: where the metric of the
    `NonholonomicSystem` depends on $q$ (every column of the matrix then differentiates
    $M(q)^{-1}$), or where the step has more than `KEPT_ABOVE_UNKNOWNS` unknowns,
    `unknowns(n, k)` for $n$ coordinates and $k$ constraint rows."""
    q, _ = y0
    rows = jax.eval_shape(system.constraints, q, args).shape[0]
    return metric_is(metric_of(system, y0, args), "position") or unknowns(q.shape[0], rows) > KEPT_ABOVE_UNKNOWNS


def check_optional_bool(owner: str, name: str, value) -> None:
    """A `ValueError` naming `owner`'s option `name` unless `value` is `None`, `True` or
    `False` (a choice that `None` leaves to the method)."""
    if not (value is None or isinstance(value, bool)):
        raise ValueError(f"{owner}: {name} must be None, True or False, got {value!r}.")


def check_positive_int(owner: str, name: str, value) -> None:
    """A `ValueError` naming `owner`'s option `name` unless `value` is a positive int (a
    bool is not one)."""
    if not is_int(value) or value < 1:
        raise ValueError(f"{owner}: {name} must be a positive int, got {value!r}.")


def is_nhjax_solver(solver) -> bool:
    """Whether `solver` is one of nhjax's (a method, a composition, a projection): each
    says what it keeps (`keeps_constraint`), diffrax's solvers do not. A composition is
    no `AbstractMethod`."""
    return hasattr(solver, "keeps_constraint")


# How many step displacements the predictors of GONZALEZ-R and of EP-collocation keep
# (`displacements_for_step`): on the gearbox at h = 0.05, GONZALEZ-R's guess from the
# last six is 2e3 times closer than the one from the last two, on Euler's disk at
# h = 0.01 8e4 times.
HISTORY = 6
# A prediction from the history is taken where it agrees with the one from the last
# step or two to this fraction of its size (`agrees`).
AGREEMENT = 1e-2


def displacements_for_step(continues, h, last_step, displacements: Float[Array, "m n"]) -> Float[Array, "m n"]:
    r"""The displacements $x_{k-j} - x_{k-j-1}$ of the last `HISTORY` steps, newest
    first, that a step of size `h` may read: those carried, where the step continues
    the last one and has its size (to `CHORD_KEY_TOLERANCE`: sizes from accumulated
    times differ by rounding), NaN otherwise; a step size changed, they describe
    another sequence of points and the history starts again."""
    same_size = continues & (jnp.abs(h - last_step) <= CHORD_KEY_TOLERANCE * jnp.abs(h))
    return jnp.where(same_size, displacements, jnp.nan)


def with_displacement(displacements: Float[Array, "m n"], newest: Float[Array, " n"]) -> Float[Array, "m n"]:
    """The history after a step of displacement `newest` (no derivatives)."""
    return jnp.concatenate([lax.stop_gradient(newest)[None], displacements[:-1]])


def agrees(prediction: Array, reference: Array) -> Array:
    """Whether a prediction from the step history is within `AGREEMENT` of the one from
    the last steps (max norm), which it is where the steps are short against the
    motion and both are close, and is not where a polynomial through `HISTORY` step
    ends extrapolates wildly. False where either is NaN."""
    return jnp.max(jnp.abs(prediction - reference)) <= AGREEMENT * jnp.max(jnp.abs(reference))


def step_key(h, dtype=None, signs: Float[Array, " k"] | None = None) -> Float[Array, " c"]:
    """A `chord_key`: the step size `h` (as `dtype`), and the frame's `signs` where the
    matrix was formed in a frame."""
    key = jnp.reshape(lax.stop_gradient(jnp.asarray(h, dtype=dtype)), (1,))
    return key if signs is None else jnp.concatenate([key, signs.astype(key.dtype)])


class ChordMemory(eqx.Module):
    """The chord matrix of the last step (in the form `AbstractMethod.chord_matrix`
    returns it) and its inverse, kept for the next step
    (`AbstractMethod.reuses_chord_matrix`): `key`, what it was formed for
    (`AbstractMethod.chord_key`; NaN before the first step, so that it matches
    nothing); the iterations the step that formed it took, those of the last step, the
    steps it has served (`age`), and the chord matrices formed so far."""

    jacobian: PyTree[Array]
    inverse: Float[Array, "u u"] | tuple[Float[Array, "r u"], ...]
    key: Float[Array, " c"]
    fresh_iterations: Int[Array, ""]
    last_iterations: Int[Array, ""]
    age: Int[Array, ""]
    formed: Int[Array, ""]


class MethodState(AbstractCountingState):
    """The diffrax solver state of an nhjax method: root-finder iterations so far, the
    nhjax code of the step that failed, if one did, what the method carries from
    one step to the next (`AbstractMethod.initial_carry`), and, for a method that
    reuses its chord matrix, that matrix (`ChordMemory`)."""

    failure: RESULTS
    carry: PyTree = None
    chord: ChordMemory | None = None

    def statistics(self) -> dict[str, Array]:
        """`root_find_steps` and `max_root_find_steps` (`AbstractCountingState`), and
        for a method that reuses its chord matrix `chord_matrices`, the chord matrices
        formed (and inverted) in all."""
        statistics = super().statistics()
        if self.chord is not None:
            statistics["chord_matrices"] = self.chord.formed
        return statistics

    def record(
        self, steps: Int[Array, ""], failure: RESULTS, carry: PyTree, chord: ChordMemory | None = None
    ) -> "MethodState":
        return MethodState(
            self.total_steps + steps, jnp.maximum(self.max_steps, steps), failure, carry, chord
        )


# Points are rounded twice per residual (the midpoint and the end), each to half an
# ulp, and the chord matrix approximates the residual's Jacobian: a margin of 4.
ROUNDING_FLOOR = 4.0


def resolution_of(x: Array, scale: Array) -> Array:
    r"""$\epsilon|x|/s$: the rounding of $x + su$ in the units of $u$ (see
    `AbstractMethod.resolution`)."""
    return lax.stop_gradient(float(jnp.finfo(x.dtype).eps) * jnp.abs(x) / scale)


def rounding_floor(jacobian: Float[Array, "u u"], resolution: Float[Array, " u"], scale: Float[Array, " u"]) -> Array:
    r"""The rounding of a residual caused by the rounding of the points it evaluates
    the system at (`AbstractMethod.resolution`): $w = |\tilde J|\,r$ row by row,
    $\tilde J$ the chord matrix, and for the rows of state increments also the largest
    of these in the state's own units, $\max_j s_jw_j/s_i$: a discrete gradient's
    correction term, $(\bar\nabla H^T\hat\delta)\hat\delta$, carries the rounding of
    one component of the midpoint gradient into every component along the increment,
    which the chord matrix (built without that term) does not show. Times the margin
    `ROUNDING_FLOOR`."""
    return floor_of_rounding(jnp.abs(lax.stop_gradient(jacobian)) @ resolution, scale)


def floor_of_rounding(own: Float[Array, " u"], scale: Float[Array, " u"]) -> Array:
    r"""`rounding_floor` from $w = |\tilde J|\,r$ (for a method that forms $w$ by the
    structure of its chord matrix)."""
    increments = scale > 0
    mixed = jnp.max(scale * own) / jnp.where(increments, scale, 1.0)
    return ROUNDING_FLOOR * (own + jnp.where(increments, mixed, 0.0))


def default_root_finder(dtype) -> optx.AbstractRootFinder:
    """The chord iteration (`nhjax._solver.chord.PresetChord`) to a few ulps of the dtype.

    Every nhjax method poses its root find in scaled unknowns (`increment_scale`), so
    one absolute tolerance serves every system. The
    iteration stops when both the last correction and the residual are below it, and
    returns the corrected iterate, whose error is then a small multiple of that.
    """
    return PresetChord(atol=64 * float(jnp.finfo(dtype).eps))


def increment_scale(x: Array) -> Array:
    """The scale $s = 1 + |x|$ (elementwise, no gradient) in which a method poses the
    increment of `x`: $u = (x' - x)/s$ is O(h), and a fixed absolute tolerance on $u$
    is an absolute one for components of size below 1 and a relative one above. Per
    component, so that large components (positions far from the origin) do not loosen
    the tolerance on small ones (momenta, which set the energy)."""
    return lax.stop_gradient(1 + jnp.abs(x))


def positive_unit(x: Array) -> Array:
    """`x`, or 1 where `x` is 0 (a normalisation that must not divide by zero; a zero
    constraint matrix then shows up as a singular root-find Jacobian)."""
    x = lax.stop_gradient(x)
    return jnp.where(x > 0, x, jnp.ones_like(x))


class AbstractMethod(diffrax.AbstractSolver):
    r"""A one-step method whose step is a root find: the generic stepper.

    A method says how a step is posed and what its root gives:

    - `setup(system, t, h, y0, args, carry) -> (guess, data)`: for the step from time
      `t` to `t + h`, the initial guess for the unknowns (a 1-D array) and everything
      the residual needs;
    - `residual(unknowns, data)`, whose root is the step, and
      `root_find_residual(unknowns, data)`, the same values computed without what only
      the residual's derivatives need (by default the residual itself): the chord
      iteration evaluates it and never differentiates it, while the derivatives of the
      root (`_implicit_root`) and derivative-based root finders use `residual`;
    - `simplified_residual(unknowns, data)`: a cheaper function with nearly the same
      Jacobian (see `nhjax._solver.chord`), whose Jacobian at the guess,
      `chord_jacobian(unknowns, data)` (by default `jax.jacfwd`), the default chord root
      finder uses; by default the residual itself;
    - `complete(unknowns, data) -> (y1, carry)`: the new state, and what the next step
      receives as `carry` (the first step receives `initial_carry(system, y0, args)`,
      by default `None`; a run's derivative stores per step only `replayed_carry` of
      it).

    Subclasses set `root_finder` (`None`: `default_root_finder` for the state's dtype)
    and `root_find_max_steps`, and say whether the method is symmetric
    (`is_symmetric`, `adjoint`, `composition_obstacle`: what `nhjax.Composition`
    needs). `advance(system, t, h, y0, args, state)` takes one step of signed size `h`
    from time `t`; `step` is diffrax's interface to it. A forced run's states carry
    their energy ledger (`nhjax._ledger.Ledgered`): `advance` and `replay_step` step
    the state and add the step's `exchange` to the ledger, taken with the residual
    from `residual_and_exchange`, so that their derivatives share one linearisation
    (`_implicit_root_and_exchange`).
    """

    interpolation_cls: ClassVar = diffrax.LocalLinearInterpolation

    # diffrax's `AbstractImplicitSolver` declares these two as well, but a method is not
    # one: `diffrax.diffeqsolve` rewrites an implicit solver's root-finder tolerances
    # from the step-size controller, and `root_finder=None` (the default for the
    # state's dtype, `default_root_finder`) has none to rewrite.
    root_finder: eqx.AbstractVar[optx.AbstractRootFinder | None]
    root_find_max_steps: eqx.AbstractVar[int]

    def __check_init__(self):
        # Zero iterations leave every step unsolved, which a run reported as a
        # non-finite state.
        check_positive_int(type(self).__name__, "root_find_max_steps", self.root_find_max_steps)
        if not (self.root_finder is None or isinstance(self.root_finder, optx.AbstractRootFinder)):
            raise ValueError(
                f"{type(self).__name__}: root_finder must be None (the chord iteration) or an optimistix "
                f"root finder such as optimistix.Newton(rtol, atol), got {self.root_finder!r}."
            )

    def initial_carry(self, system: AbstractSystem, y0: PyTree[Array], args: PyTree) -> PyTree:
        del system, y0, args
        return None

    def setup(
        self, system: AbstractSystem, t: Scalar, h: Scalar, y0: PyTree[Array], args: PyTree, carry: PyTree
    ) -> tuple[Float[Array, " u"], Any]:
        raise NotImplementedError

    def exchange(self, unknowns: Float[Array, " u"], data: Any) -> tuple[Array, Array]:
        raise ValueError(
            f"{type(self).__name__} does not take a system with a force or a dissipation: it "
            "has no discrete energy exchange (AbstractMethod.exchange)."
        )

    def residual(self, unknowns: Float[Array, " u"], data: Any) -> Float[Array, " u"]:
        raise NotImplementedError

    def residual_and_exchange(self, unknowns: Float[Array, " u"], data: Any) -> tuple[Array, tuple[Array, Array]]:
        """`residual` and `exchange` at `unknowns`; a method whose two share their
        evaluation computes them once."""
        return self.residual(unknowns, data), self.exchange(unknowns, data)

    def root_find_residual(self, unknowns: Float[Array, " u"], data: Any) -> Float[Array, " u"]:
        return self.residual(unknowns, data)

    def simplified_residual(self, unknowns: Float[Array, " u"], data: Any) -> Float[Array, " u"]:
        return self.residual(unknowns, data)

    def chord_jacobian(self, unknowns: Float[Array, " u"], data: Any) -> Float[Array, "u u"]:
        return jax.jacfwd(self.simplified_residual)(unknowns, data)

    def chord_matrix(
        self, unknowns: Float[Array, " u"], data: Any, kept: bool = False
    ) -> tuple[PyTree[Array], Float[Array, "u u"] | tuple[Float[Array, "r u"], ...]]:
        """The chord matrix at `unknowns` (`chord_jacobian`) and its inverse, by default
        `nhjax._solver.chord.chord_inverse` (`kept`: for a matrix kept from step to step,
        `reuses_chord_matrix`, formed at a few steps). A method whose matrix has structure may form and
        invert it by that structure, and return in its place what it forms it from (its
        `chord_floor` reads that; a step fails as non-finite where any of it is), and
        may return the inverse as blocks of rows (`nhjax._linalg.row_blocks`), formed
        as they are, never the whole matrix
        (`nhjax.EnergyPreservingCollocation.chord_matrix`)."""
        jacobian = self.chord_jacobian(unknowns, data)
        return jacobian, chord_inverse(jacobian, kept)

    def unformed_chord_matrix(self, unknowns: Float[Array, " u"], data: Any) -> PyTree[Array]:
        """NaN in the form of `chord_matrix`'s output, for a kept chord matrix's memory
        before any matrix is formed (`reuses_chord_matrix`). Read off the unknowns
        where `chord_matrix` is this class's, a square matrix and its inverse: tracing
        it for its shapes alone would trace the residual as often as forming it does.
        A method with its own `chord_matrix` has it traced for its shapes
        (`jax.eval_shape`)."""
        if type(self).chord_matrix is not AbstractMethod.chord_matrix:
            shapes = jax.eval_shape(lambda: self.chord_matrix(unknowns, data, kept=True))
            return jax.tree.map(lambda leaf: jnp.full(leaf.shape, jnp.nan, leaf.dtype), shapes)
        square = jnp.full((unknowns.shape[0],) * 2, jnp.nan, unknowns.dtype)
        return square, square

    def chord_floor(self, matrix: PyTree[Array], data: Any) -> Float[Array, " u"] | None:
        """The rounding floor of the residual (`rounding_floor`) from the chord matrix as
        `chord_matrix` returns it, at the method's `resolution`; `None` where it has
        none."""
        resolution = self.resolution(data)
        return None if resolution is None else rounding_floor(matrix, *resolution)

    def complete(self, unknowns: Float[Array, " u"], data: Any) -> tuple[PyTree[Array], PyTree]:
        raise NotImplementedError

    def chord_remainder(self, data: Any) -> float | None:
        """A bound on the error the chord iteration may leave in the returned iterate,
        in units of its tolerance (`nhjax._solver.chord.PresetChord.solve`), for a
        method whose chord matrix contracts slowly; `None` (the default): none beyond
        the tolerance."""
        del data
        return None

    def resolution(self, data: Any) -> tuple[Float[Array, " u"], Float[Array, " u"]] | None:
        r"""How finely the points at which the residual evaluates the system are
        resolved: for each unknown $u_j = (x'_j - x_j)/s_j$, the rounding of
        $x_j + s_ju_j$ in the units of $u_j$, $\epsilon|x_j|/s_j$ (`resolution_of`), and
        the scale $s_j$ (0 for unknowns that are not increments of the state, such as
        impulses). `None` (the default): no floor.

        The chord iteration's tolerance then has a floor (`rounding_floor`,
        `nhjax._solver.chord.PresetChord`): a coordinate far from the origin, such as
        an angle wound up over a long run, is held only to $\epsilon$ times its size,
        and what depends on it only to that, whatever the tolerance asks."""
        del data
        return None

    def reuses_chord_matrix(self, system: AbstractSystem, y0: PyTree[Array], args: Any) -> bool:
        r"""Whether a step starts from the last step's chord matrix and its inverse
        (`ChordMemory`) instead of forming them, as implicit Runge--Kutta codes keep
        their simplified-Newton matrix over steps (Hairer & Wanner, *Solving ODEs II*,
        §IV.8). A kept matrix is used while it was formed for the same `chord_key` (the
        step size, and whatever else it depends on; to `CHORD_KEY_TOLERANCE`, as step
        sizes from accumulated times differ by rounding), for at most `KEPT_STEPS`
        steps, and while the last step took at most one iteration more than twice
        those of the step that formed it; a root find that fails with a kept matrix is
        repeated with a fresh one. So only the iteration count,
        not the root (to the root finder's tolerance) or whether a step succeeds,
        depends on it, and derivatives, which come from the implicit function theorem
        with the exact Jacobian, not at all. It pays where forming the matrix costs several
        iterations (a metric that depends on $q$, many unknowns), and costs where the
        extra iterations a kept matrix needs are dear against it
        (`benchmarks/chord_reuse.py` measures both). Decided once for a run, from
        its system, start and `args` (at trace time). Default: no; the methods that
        offer it take `reuse_chord_matrix`."""
        del system, y0, args
        return False

    def chord_key(self, data: Any) -> Float[Array, " c"]:
        """What the chord matrix of a step with `data` depends on besides the point it is
        formed at (`reuses_chord_matrix`): by default the step size `data.h`
        (`step_key`)."""
        return step_key(data.h)

    def init(self, terms, t0, t1, y0, args) -> MethodState:
        system, _ = self.system_and_step(terms, t0, t1)
        zero = jnp.array(0, dtype=jnp.int32)
        state = unledgered(y0)
        carry = self.initial_carry(system, state, args)
        chord = None
        chord_finder = isinstance(self._root_finder(jax.tree.leaves(y0)[0].dtype), PresetChord)
        if chord_finder and self.reuses_chord_matrix(system, state, args):

            def matrix_and_key():
                guess, data = self.setup(system, t0, t1 - t0, state, args, carry)
                return self.unformed_chord_matrix(guess, data), self.chord_key(data)

            (jacobian, inverse), key = jax.tree.map(
                lambda leaf: jnp.full(leaf.shape, jnp.nan, leaf.dtype), jax.eval_shape(matrix_and_key)
            )
            chord = ChordMemory(
                jacobian,
                inverse,
                key,
                zero,
                zero,
                zero,
                zero,
            )
        return MethodState(zero, zero, RESULTS.successful, carry, chord)

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    @staticmethod
    def system_and_step(terms, t0, t1):
        """The user's system inside diffrax's wrappers (`unwrapped_system`), and the
        signed step size (diffrax integrates backward in time by negating times inside a
        wrapper)."""
        return unwrapped_system(terms), terms.contr(t0, t1)

    def _root_finder(self, dtype) -> optx.AbstractRootFinder:
        return default_root_finder(dtype) if self.root_finder is None else self.root_finder

    def keeps_energy(self) -> bool:
        """Whether every step keeps the energy $H$ to roundoff."""
        raise NotImplementedError

    def keeps_constraint(self) -> bool:
        """Whether every step keeps the constraint to roundoff."""
        raise NotImplementedError

    def summary(self) -> str:
        """What the method is, in a line (the command line's and the reproduction's
        description of it adds its order and what it keeps)."""
        return type(self).__name__

    def is_symmetric(self) -> bool:
        r"""Whether the method is its own adjoint, $\Phi_{-h} = \Phi_h^{-1}$ (time-symmetric),
        as `nhjax.Composition` requires of the methods it composes. `False` unless a
        method says otherwise."""
        return False

    def composition_obstacle(self) -> str | None:
        """Why composing this method (`nhjax.Composition`) would not raise its order even
        though it is symmetric, or `None` where nothing stands in the way."""
        return None

    def adjoint(self) -> "AbstractMethod | None":
        r"""The adjoint method $\Phi^*_h = \Phi_{-h}^{-1}$, or `None` where it is not
        available as a method: `self` for a symmetric method."""
        return self if self.is_symmetric() else None

    def step(
        self, terms, t0: Scalar, t1: Scalar, y0: PyTree[Array], args: PyTree, solver_state: MethodState, made_jump
    ) -> tuple[PyTree[Array], None, dict[str, PyTree[Array]], MethodState, diffrax.RESULTS]:
        del made_jump
        system, h = self.system_and_step(terms, t0, t1)
        y1, solver_state, failure = self.advance(system, t0, h, y0, args, solver_state)
        return step_return(y0, y1, solver_state, failure)

    def advance(
        self, system: AbstractSystem, t: Scalar, h: Scalar, y0: PyTree[Array], args: PyTree, solver_state: MethodState
    ) -> tuple[PyTree[Array], MethodState, RESULTS]:
        """One step of signed size `h` from `y0` at time `t`: the new state (not yet
        replaced by NaN on failure, see `step_return`), the method state after it, and
        the step's code (`step_failure`). A `Ledgered` state's ledger gains the step's
        `exchange`.

        diffrax traces a solver's step several times (to learn its output structure,
        then in its loop, and again for derivatives), so `solve_step` runs the step
        through `_traced_once`, a `jax.jit` call with the method, the system and the
        static arguments as its static arguments: JAX traces it once for them and the
        shapes of the rest, and reuses the trace."""
        y1, solver_state, failure, _ = self.solve_step(system, t, h, y0, args, solver_state)
        return y1, solver_state, failure

    def solve_step(
        self, system: AbstractSystem, t: Scalar, h: Scalar, y0: PyTree[Array], args: PyTree, solver_state: MethodState
    ) -> tuple[PyTree[Array], MethodState, RESULTS, Float[Array, " u"]]:
        """`advance`, and the root of the step's equations, which `replay_step` turns
        into the same step again without the root finder."""
        return _traced_once(self, system, t, h, y0, args, solver_state)

    def replay_step(
        self,
        system: AbstractSystem,
        t: Scalar,
        h: Scalar,
        y0: PyTree[Array],
        args: PyTree,
        carry: PyTree,
        root: Float[Array, " u"],
    ) -> tuple[PyTree[Array], PyTree]:
        r"""The new state and carry of the step from `y0` whose root `solve_step`
        returned: the same values as `advance` (from the same setup and completion,
        with `root` in place of the root finder's answer), and the derivatives the
        implicit function theorem gives the step (`_implicit_root`). For derivatives of
        a whole run without the root finder in them (`nhjax._replay`).

        The carry is taken and returned as `replayed_carry` keeps it: what it drops
        only guesses the root, which the replay does not seek, and reads as NaN."""
        template = jax.eval_shape(lambda: self.initial_carry(system, unledgered(y0), args))
        carry = jax.tree.map(
            lambda kept, shape: jnp.full(shape.shape, jnp.nan, shape.dtype) if kept is None and shape is not None else kept,
            carry,
            template,
            is_leaf=lambda leaf: leaf is None,
        )
        _, data = self.setup(system, t, h, unledgered(y0), args, carry)
        y1, carry, _ = self._completed(y0, lax.stop_gradient(root), data, replayed=True)
        return y1, self.replayed_carry(carry)

    def replayed_carry(self, carry: PyTree) -> PyTree:
        """The part of a step's carry that a replayed step (`replay_step`) reads: all of
        it, unless a method drops (as `None`) what only its guess of the root reads.
        A run's derivative stores this per step (`nhjax._replay`): what is dropped is
        memory saved at every step, and longer runs fit the replay's budget
        (`nhjax._adjoints.replays_derivatives`) instead of falling back to diffrax's
        checkpointed loop."""
        return carry

    def _completed(self, y0, root, data, replayed: bool = False):
        r"""The step from `y0` whose root is `root`, with the root's derivatives
        (`_implicit_root`): the new state (with `y0`'s ledger, if it has one, after the
        step's exchange, whose derivatives share the root's linearisation,
        `_implicit_root_and_exchange`), the carry, and whether the exchange is finite."""
        if not isinstance(y0, Ledgered):
            root = _implicit_root(root, data, residual=self.residual, replayed=replayed)
            y1, carry = self.complete(root, data)
            return y1, carry, jnp.array(True)
        root, (supplied, dissipated) = _implicit_root_and_exchange(
            root, data, residual=self.residual, equations=self.residual_and_exchange, replayed=replayed
        )
        y1, carry = self.complete(root, data)
        finite = jnp.isfinite(supplied) & jnp.isfinite(dissipated)
        return y0.after(y1, supplied, dissipated), carry, finite

    def _advance(self, system, t, h, y0, args, solver_state):
        start = y0
        y0 = unledgered(y0)
        guess, data = self.setup(system, t, h, y0, args, solver_state.carry)
        # The root find runs on constants; its derivatives come from `_implicit_root`.
        guess, fixed_data = lax.stop_gradient(guess), no_gradient(data)
        root_finder = self._root_finder(guess.dtype)
        chord = None
        if isinstance(root_finder, PresetChord):
            solution, jacobian, inverse, chord = self._chord_solve(root_finder, guess, fixed_data, solver_state.chord)
            evaluations_finite = jnp.all(jnp.isfinite(guess)) & all_finite(jacobian)
            singular = ~all_finite(inverse)
        else:
            found = optx.root_find(
                self.residual, root_finder, guess, fixed_data, max_steps=self.root_find_max_steps, throw=False
            )
            residual_size = jnp.max(jnp.abs(self.residual(found.value, fixed_data)))
            solution = ChordSolution(found.value, found.result, found.stats["num_steps"], residual_size)
            evaluations_finite = jnp.all(jnp.isfinite(guess))
            singular = jnp.array(False)
        evaluations_finite = evaluations_finite & jnp.isfinite(solution.residual_size)
        entered, carry, exchange_finite = self._completed(start, solution.value, data)
        y1 = unledgered(entered)
        failure = step_failure(
            evaluations_finite & exchange_finite,
            all_finite(y1),
            system.step_result(y0, y1, args),
            singular,
            solution.result,
        )
        return entered, solver_state.record(solution.steps, failure, carry, chord), failure, solution.value

    def _fresh_chord(self, operands, kept: bool = False):
        """The chord matrix at the guess, and its inverse (`kept`: to be kept for the
        steps after, `chord_matrix`)."""
        return self.chord_matrix(*operands, kept=kept)

    def _chord_root(self, root_finder, guess, data, jacobian, inverse) -> ChordSolution:
        return root_finder.solve(
            self.root_find_residual,
            guess,
            data,
            inverse,
            self.root_find_max_steps,
            self.chord_floor(jacobian, data),
            self.chord_remainder(data),
        )

    def _fresh_chord_root(self, root_finder, operands):
        """`_chord_root` with a fresh chord matrix: the solution, the matrix and its
        inverse."""
        jacobian, inverse = self._fresh_chord(operands)
        return self._chord_root(root_finder, *operands, jacobian, inverse), jacobian, inverse

    def _chord_solve(self, root_finder, guess, data, memory: ChordMemory | None):
        """The chord iteration of a step (constants only), with a fresh chord matrix or,
        for a method that reuses it (`reuses_chord_matrix`), the kept one where it
        serves: the solution (its iterations counting a repeat with a fresh matrix),
        the matrix and inverse used, and the memory for the next step.

        The repeat is a second trip through the same loop, not a second copy of the
        matrix and of the iteration: the step's program then holds one of each, as
        without reuse (a copy of each made the program half as large again, and its
        compilation as much slower).

        The loop's condition reads its trip count beside the repeat flag, though the
        flag alone decides (a second trip is one with a fresh matrix, which never
        repeats). XLA looks for an induction variable in every while loop, at every
        run of its loop passes (loop-invariant code motion and the loop simplifier,
        some 17 runs each): where the condition reads one element of the carry, it
        extracts that element's whole computation in the body into a module of its
        own to check it, here the chord iteration with its matrix, every run; a
        condition on two elements ends the search at once. Euler's disk
        (`nhjax.examples.rolling_disk_3d`, GONZALEZ-R, 2 000 steps) compiled in 5.1 s
        against 6.7 s from its mass matrix and in 5.2 s against 6.0 s from its
        Lagrangian (medians of three, one process each, in turns, on a 2-core
        machine), and at the test suite's settings in 5.0 s against 8.7 s, the same
        program otherwise and the same results to the bit (`python
        benchmarks/scaling.py --parts disk` times its compilation)."""
        if memory is None:
            return *self._fresh_chord_root(root_finder, (guess, data)), None
        key = self.chord_key(data)
        kept = (
            jnp.all(jnp.abs(memory.key - key) <= CHORD_KEY_TOLERANCE * jnp.abs(key))
            & (memory.age < KEPT_STEPS)
            & (memory.last_iterations <= 2 * memory.fresh_iterations + 1)
            & all_finite(memory.inverse)
        )

        def attempt(carry):
            fresh, _, steps_before, _, jacobian, inverse, trips = carry
            jacobian, inverse = rarely(
                fresh, functools.partial(self._fresh_chord, kept=True), (jacobian, inverse), (guess, data)
            )
            solution = self._chord_root(root_finder, guess, data, jacobian, inverse)
            failed = (solution.result != optx.RESULTS.successful) | ~jnp.isfinite(solution.residual_size)
            # A failure with a kept matrix is repeated with a fresh one; after the last
            # trip, `fresh` says whether it formed the matrix.
            repeat = ~fresh & failed
            return fresh | repeat, repeat, steps_before + solution.steps, solution, jacobian, inverse, trips + 1

        def repeats(carry):
            _, repeat, _, _, _, _, trips = carry
            return repeat & (trips < 2)

        # The iteration counts in the default integer type, as the root finder's.
        zero = jnp.asarray(0)
        unstarted = ChordSolution(guess, optx.RESULTS.successful, zero, jnp.zeros((), guess.dtype))
        start = (~kept, jnp.asarray(True), zero, unstarted, memory.jacobian, memory.inverse, zero)
        fresh, _, steps, last, jacobian, inverse, _ = lax.while_loop(repeats, attempt, start)
        solution = ChordSolution(last.value, last.result, steps, last.residual_size)
        iterations = last.steps.astype(memory.last_iterations.dtype)
        memory = ChordMemory(
            jacobian,
            inverse,
            key,
            jnp.where(fresh, iterations, memory.fresh_iterations),
            iterations,
            jnp.where(fresh, 1, memory.age + 1).astype(memory.age.dtype),
            memory.formed + fresh.astype(memory.formed.dtype),
        )
        return solution, jacobian, inverse, memory


@eqx.filter_jit
def _traced_once(method: AbstractMethod, system: AbstractSystem, t, h, y0, args, solver_state: MethodState):
    return method._advance(system, t, h, y0, args, solver_state)


class AbstractSymmetricSecondOrderMethod(AbstractMethod):
    r"""A method that is second order and its own adjoint ($\Phi_{-h} = \Phi_h^{-1}$):
    GONZALEZ-R, GONZALEZ-F, SI-DLA and I-DLA."""

    def order(self, terms) -> int:
        del terms
        return 2

    def is_symmetric(self) -> bool:
        return True


def step_return(y0, y1, solver_state, failure: RESULTS):
    """The return tuple of a diffrax step. A failed step returns NaN, never a
    plausible-looking state, with NaN derivatives with respect to `y0`
    (`nan_where_failed`); diffrax receives `breakdown`, and the nhjax code travels in
    `solver_state` (see the module docstring)."""
    failed = failure != RESULTS.successful
    result = diffrax.RESULTS.where(failed, diffrax.RESULTS.breakdown, diffrax.RESULTS.successful)
    y1 = nan_where_failed(failed, y1, y0)
    dense_info = dict(y0=y0, y1=y1)
    return y1, None, dense_info, solver_state, result


def all_finite(tree: PyTree) -> Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(tree)]))


def step_failure(evaluations_finite, end_finite, system_result, singular, root_find_result) -> RESULTS:
    """The code of a step, naming the first cause in this order:

    1. the system's functions returned NaN or inf at the guess or at an iterate, or
       the new state is not finite: `nonfinite_step` (the root finder would otherwise
       report its own failure, a consequence);
    2. a failure the system sees in the step (`AbstractSystem.step_result`), such as
       $A$ losing rank (`NonholonomicSystem.rank_result`), checked at the last iterate
       even when the root find failed, since across a rank loss the step's equations
       may have no root;
    3. a singular chord matrix: `root_find_singular`;
    4. the root finder's own failure: `root_find_not_converged` (or its translation of
       another optimistix code).
    """
    root_find = from_diffrax(diffrax.RESULTS.promote(root_find_result))
    return first_failure(
        RESULTS.where(evaluations_finite & end_finite, RESULTS.successful, RESULTS.nonfinite_step),
        system_result,
        RESULTS.where(singular, RESULTS.root_find_singular, RESULTS.successful),
        root_find,
    )
