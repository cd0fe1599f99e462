"""What every nhjax method shares: an optimistix root find per step, with tolerances
that follow the dtype, per-step result codes, and root-finder statistics carried in the
diffrax solver state.

diffrax's loop accepts only its own result codes from a step, so a failure that only an
nhjax method can name (such as a constraint matrix losing rank) travels in the solver
state as an `nhjax.RESULTS` code, while the step reports `diffrax.RESULTS.breakdown`;
`nhjax.integrate` reports the nhjax code."""

from typing import Any, ClassVar

import diffrax
import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Int, PyTree

from .._results import nan_where_failed, RESULTS
from .._system import AbstractSystem
from .chord import Chord, invert


def _no_gradient(tree: PyTree) -> PyTree:
    arrays, static = eqx.partition(tree, eqx.is_array)
    return eqx.combine(lax.stop_gradient(arrays), static)


@eqx.filter_custom_jvp
def _implicit_root(root, data, *, residual):
    r"""`root`, a root of `residual(., data)`, with the derivatives the implicit function
    theorem gives it: $\dot u = -(\partial_u F)^{-1}\,\partial_{\text{data}}F\,
    \dot{\text{data}}$, with the exact Jacobian $\partial_u F$ at the root.

    This is what optimistix's `ImplicitAdjoint` computes, done here because its lineax
    solve raises a runtime error when it meets a non-finite value, and under `vmap` one
    failed trajectory (whose states are NaN from the failure on) would then stop the
    derivatives of the whole batch. Here a failed trajectory's derivatives are NaN and
    its neighbours' are unaffected."""
    del data, residual
    return root


@_implicit_root.def_jvp
def _implicit_root_jvp(primals, tangents, *, residual):
    root, data = primals
    _, data_tangent = tangents
    jacobian = jax.jacfwd(residual)(root, _no_gradient(data))
    differentiable = jax.tree.map(lambda t: t is not None, data_tangent, is_leaf=lambda t: t is None)
    varying, fixed = eqx.partition(data, differentiable)
    tangent_in = eqx.filter(data_tangent, differentiable, is_leaf=lambda t: t is None)
    _, residual_tangent = jax.jvp(
        lambda v: residual(root, eqx.combine(v, fixed)), (varying,), (tangent_in,)
    )
    return root, -jnp.linalg.solve(jacobian, residual_tangent)


class MethodState(eqx.Module):
    """The diffrax solver state of an nhjax method: root-finder iterations so far, the
    nhjax code of the step that failed, if one did, and what the method carries from
    one step to the next (`AbstractMethod.initial_carry`)."""

    total_steps: Int[Array, ""]
    max_steps: Int[Array, ""]
    failure: RESULTS
    carry: PyTree = None

    def record(self, steps: Int[Array, ""], failure: RESULTS, carry: PyTree) -> "MethodState":
        return MethodState(
            self.total_steps + steps, jnp.maximum(self.max_steps, steps), failure, carry
        )


def default_root_finder(dtype) -> optx.AbstractRootFinder:
    """The chord iteration (`nhjax._solver.chord.Chord`) to a few ulps of the dtype.

    Every nhjax method poses its root find in scaled unknowns (`increment_scale`), so
    one absolute tolerance serves every system. The
    iteration stops when both the last correction and the residual are below it, and
    returns the corrected iterate, whose error is then a small multiple of that.
    """
    return Chord(atol=64 * float(jnp.finfo(dtype).eps))


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

    - `setup(system, h, y0, args, carry) -> (guess, data)`: the initial guess for the
      unknowns (a 1-D array) and everything the residual needs;
    - `residual(unknowns, data)`, whose root is the step;
    - `simplified_residual(unknowns, data)`: a cheaper function with nearly the same
      Jacobian (see `nhjax._solver.chord`), whose Jacobian at the guess,
      `chord_jacobian(unknowns, data)` (by default `jax.jacfwd`), the default chord root
      finder uses; by default the residual itself;
    - `complete(unknowns, data) -> (y1, failure, carry)`: the new state, an nhjax code
      for failures only the method can detect, and what the next step receives as
      `carry` (the first step receives `initial_carry(system, y0, args)`, by default
      `None`).

    Subclasses set `root_finder` (`None`: `default_root_finder` for the state's dtype)
    and `root_find_max_steps`.
    """

    interpolation_cls: ClassVar = diffrax.LocalLinearInterpolation

    root_finder: eqx.AbstractVar[optx.AbstractRootFinder | None]
    root_find_max_steps: eqx.AbstractVar[int]

    def initial_carry(self, system, y0, args) -> PyTree:
        del system, y0, args
        return None

    def setup(self, system, h, y0, args, carry) -> tuple[Array, Any]:
        raise NotImplementedError

    def residual(self, unknowns, data) -> Array:
        raise NotImplementedError

    def simplified_residual(self, unknowns, data) -> Array:
        return self.residual(unknowns, data)

    def chord_jacobian(self, unknowns, data) -> Array:
        return jax.jacfwd(self.simplified_residual)(unknowns, data)

    def complete(self, unknowns, data) -> tuple[Any, RESULTS, PyTree]:
        raise NotImplementedError

    def init(self, terms, t0, t1, y0, args) -> MethodState:
        system, _ = self.system_and_step(terms, t0, t1)
        zero = jnp.array(0, dtype=jnp.int32)
        return MethodState(zero, zero, RESULTS.successful, self.initial_carry(system, y0, args))

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    @staticmethod
    def system_and_step(terms, t0, t1):
        """The user's system inside diffrax's wrappers, and the signed step size (diffrax
        integrates backward in time by negating times inside a wrapper)."""
        system = terms
        while not isinstance(system, AbstractSystem):
            system = system.term
        return system, terms.contr(t0, t1)

    def _root_finder(self, dtype) -> optx.AbstractRootFinder:
        return default_root_finder(dtype) if self.root_finder is None else self.root_finder

    def step(self, terms, t0, t1, y0, args, solver_state: MethodState, made_jump):
        del made_jump
        system, h = self.system_and_step(terms, t0, t1)
        guess, data = self.setup(system, h, y0, args, solver_state.carry)
        # The root find runs on constants; its derivatives come from `_implicit_root`.
        guess, fixed_data = lax.stop_gradient(guess), _no_gradient(data)
        root_finder = self._root_finder(guess.dtype)
        options = {}
        if isinstance(root_finder, Chord):
            options["inverse"] = invert(self.chord_jacobian(guess, fixed_data))
        solution = optx.root_find(
            self.residual,
            root_finder,
            guess,
            fixed_data,
            options=options,
            max_steps=self.root_find_max_steps,
            throw=False,
        )
        result = diffrax.RESULTS.promote(solution.result)
        root = _implicit_root(solution.value, data, residual=self.residual)
        y1, failure, carry = self.complete(root, data)
        state = solver_state.record(solution.stats["num_steps"], failure, carry)
        return self.finish(y0, y1, result, state, failure)

    @staticmethod
    def finish(y0, y1, result, solver_state: MethodState, failure=RESULTS.successful):
        """The step's return tuple. A failed or non-finite step returns NaN, never a
        plausible-looking state, together with its result code, and its derivatives
        with respect to `y0` are NaN too (`nan_where_failed`). `failure` is a code the
        method detected itself (see the module docstring)."""
        result = diffrax.RESULTS.where(
            failure == RESULTS.successful, result, diffrax.RESULTS.breakdown
        )
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(y1)]))
        result = diffrax.RESULTS.where(
            (result == diffrax.RESULTS.successful) & ~finite,
            diffrax.RESULTS.nonfinite,
            result,
        )
        y1 = nan_where_failed(result != diffrax.RESULTS.successful, y1, y0)
        dense_info = dict(y0=y0, y1=y1)
        return y1, None, dense_info, solver_state, result
