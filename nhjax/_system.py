r"""What is simulated: systems as diffrax terms built from pure JAX functions.

A system knows its equations, its energy and how to validate an initial state. It says
nothing about how a step is taken (the methods, `nhjax._solver`) or how steps are strung
together (`nhjax.integrate`). Systems are `diffrax.AbstractTerm`s whose `vf` is the
continuous vector field, so any diffrax solver can also integrate them directly.
"""

import abc
import numbers
from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ._ledger import Ledgered
from ._results import first_failure, RESULTS
from ._user_function import check_function, traced_once


class AbstractSystem(diffrax.AbstractTerm):
    """A system: a diffrax term with an energy and an initial-state check; conservative
    unless it has a dissipation or a force (`is_forced`), whose power it then reports
    (`power`). Its vector field is `field`; `vf`, diffrax's name for it, also takes a
    forced run's state with its energy ledger (`nhjax._ledger.Ledgered`)."""

    @abc.abstractmethod
    def field(self, t, y, args: Any):
        r"""The vector field $\dot y$ at time `t` and state `y`."""

    def vf(self, t, y, args):
        """`field`; on a forced run's `Ledgered` state, the field and the rates of the
        ledger, the power supplied and dissipated (`power`), so that a diffrax solver
        integrates the work and the dissipated energy with the state."""
        if isinstance(y, Ledgered):
            return Ledgered(self.field(t, y.state, args), *self.power(t, y.state, args))
        return self.field(t, y, args)

    @abc.abstractmethod
    def energy(self, y, args: Any) -> Float[Array, ""]:
        """The conserved energy at the state `y`."""

    @abc.abstractmethod
    def check_shapes(self, y0, args: Any) -> None:
        """Raise a `ValueError` naming the problem if `y0` or the user's functions have
        the wrong shapes or dtypes. Runs at trace time: costs nothing at run time."""

    @abc.abstractmethod
    def initial_state_result(self, y0, args: Any) -> RESULTS:
        """`RESULTS.successful`, or the code saying why `y0` cannot be integrated."""

    def step_result(self, y0, y1, args: Any) -> RESULTS:
        """A failure that a step from `y0` to `y1` reveals about the system itself
        (success by default; a `NonholonomicSystem` checks the rank of its
        constraints)."""
        del y0, y1, args
        return RESULTS.successful

    def observables(self, y, args: Any) -> dict[str, Array]:
        """What `nhjax.integrate` records beside the state at each save."""
        return {"energy": self.energy(y, args)}

    def is_forced(self) -> bool:
        """Whether the system has a dissipation or a force: its energy then changes by
        what they supply and remove (`power`)."""
        return getattr(self, "dissipation", None) is not None or getattr(self, "force", None) is not None

    def power(self, t, y, args: Any) -> tuple[Float[Array, ""], Float[Array, ""]]:
        r"""(supplied, dissipated): the rates at which the force supplies energy and the
        dissipation removes it at time `t` and state `y`, so that along the exact flow
        $\dot H = \text{supplied} - \text{dissipated}$, the dissipated part never
        negative. Zeros for a conservative system."""
        del t, args
        zero = jnp.zeros((), jax.tree.leaves(y)[0].dtype)
        return zero, zero

    def contr(self, t0, t1, **kwargs):
        del kwargs
        return t1 - t0

    def prod(self, vf, control):
        return jax.tree.map(lambda v: v * control, vf)


def is_int(value) -> bool:
    """An integer, not a bool (`True` is an `Integral` but no count or order)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def require_floating_vector(name: str, x) -> None:
    if not (eqx.is_array(x) or hasattr(x, "shape")):
        raise ValueError(
            f"{name} must be a 1-D array, got a {type(x).__name__}"
            + (" (convert it with jnp.asarray)." if isinstance(x, (list, tuple)) else ".")
        )
    if jnp.ndim(x) != 1:
        raise ValueError(
            f"{name} must be a 1-D array, got shape {jnp.shape(x)} "
            f"({type(x).__name__})."
        )
    if not jnp.issubdtype(jnp.result_type(x), jnp.floating):
        raise ValueError(f"{name} must be floating point, got dtype {jnp.result_type(x)}.")


def in_state_dtype(args: PyTree, dtype) -> PyTree:
    """`args` (after `nhjax._arguments.trace_floats`) with its real floating-point
    arrays in `dtype`, the state's: a float64 parameter would otherwise promote a
    float32 run's states to float64 within a step, which the loop's float32 buffers
    cannot take. Other leaves are kept as they are."""

    def cast(leaf):
        if hasattr(leaf, "dtype") and jnp.issubdtype(leaf.dtype, jnp.floating) and leaf.dtype != dtype:
            return jnp.asarray(leaf, dtype=dtype)
        return leaf

    return jax.tree.map(cast, args)


def check_dissipation_and_force(system, state, args, n: int, arguments: str) -> None:
    """Shapes and dtypes of a system's `dissipation` (an (n, n) matrix) and `force` (an
    (n,) vector), from `dissipation(*state, args)` and `force(t, *state, args)`, the
    time a scalar of the state's dtype; a `ValueError` naming the problem."""
    dtype = jnp.result_type(*jax.tree.leaves(state))
    time = jax.ShapeDtypeStruct((), dtype)
    args = in_state_dtype(args, dtype)
    for name, function, leading, shape in (
        ("dissipation", system.dissipation, (), (n, n)),
        ("force", system.force, (time,), (n,)),
    ):
        if function is None:
            continue
        signature = f"{name}({'t, ' * len(leading)}{arguments}, args)"
        struct = jax.eval_shape(function, *leading, *state, args)
        if getattr(struct, "shape", None) != shape:
            raise ValueError(f"{signature} must return shape {shape}, got {getattr(struct, 'shape', struct)}.")
        if struct.dtype != dtype:
            raise ValueError(f"{signature} must return the state's dtype {dtype}, got {struct.dtype}.")


def dissipation_at_start(dissipation, state, args) -> tuple[Array, RESULTS]:
    """Whether `dissipation(*state, args)` is finite, and
    `RESULTS.dissipation_not_positive_semidefinite` unless it is symmetric and positive
    semidefinite to 100 eps relative to its largest entry; `(True, success)` for a
    system without a dissipation."""
    if dissipation is None:
        return jnp.array(True), RESULTS.successful
    matrix = dissipation(*state, args)
    tolerance = 100 * jnp.finfo(matrix.dtype).eps * (1 + jnp.max(jnp.abs(matrix)))
    symmetric = jnp.max(jnp.abs(matrix - matrix.T)) <= tolerance
    smallest = jnp.min(jnp.linalg.eigvalsh(0.5 * (matrix + matrix.T)))
    semidefinite = RESULTS.where(
        symmetric & (smallest >= -tolerance), RESULTS.successful, RESULTS.dissipation_not_positive_semidefinite
    )
    return jnp.all(jnp.isfinite(matrix)), semidefinite


def require_state_dtype(name: str, struct, dtype) -> None:
    """A `ValueError` where `struct` (the `jax.eval_shape` of a system's function at a
    state of `dtype`, its `args` converted to `dtype` as a run converts them,
    `in_state_dtype`) is of a wider floating dtype than the state's: a method's loop
    would otherwise fail deep inside, its carry changing dtype, or differentiate in
    one dtype and step in another."""
    returned = getattr(struct, "dtype", None)
    if returned is not None and jnp.promote_types(returned, dtype) != dtype:
        raise ValueError(
            f"{name} returned {returned} for a state in {dtype}: something inside it promotes the result "
            f"(a NumPy float64 scalar or array, say; args are converted to the state's dtype). Compute it "
            f"in the state's dtype, or give the state in {returned}."
        )


def require_scalar(name: str, struct) -> None:
    if getattr(struct, "shape", None) != ():
        raise ValueError(
            f"{name} must return a scalar, got {getattr(struct, 'shape', struct)}."
        )


class SkewGradientSystem(AbstractSystem):
    r"""The skew-gradient system $\dot x = \Pi(x) \nabla H(x)$ of eq. (dynamical), or,
    with a dissipation and a force, the port-Hamiltonian form

    $$\dot x = (\Pi(x) - R(x))\nabla H(x) + g(t, x)$$

    (Celledoni & Høiseth, "Energy-preserving and passivity-consistent numerical
    discretization of port-Hamiltonian systems", arXiv:1706.08621), whose energy
    balance is $\dot H = \nabla H^Tg - \nabla H^TR\nabla H$ (`power`).

    **Arguments:**

    - `hamiltonian`: `hamiltonian(x, args) -> scalar`, the energy $H$.
    - `structure`: `structure(x, args) -> (N, N)` skew-symmetric matrix $\Pi(x)$.
    - `dissipation`: `None`, or `dissipation(x, args) -> (N, N)`, $R(x)$, symmetric
        positive semidefinite.
    - `force`: `None`, or `force(t, x, args) -> (N,)`, $g(t, x)$.

    The state is a flat array `x` of shape `(N,)`. $\nabla H$ comes from autodiff.
    Skew-symmetry of $\Pi$ is what makes $H$ conserved without $R$ and $g$; it is checked
    at the initial state (to `100 eps (1 + max|Pi|)`) by `nhjax.integrate`, and so is
    $R$ (symmetric positive semidefinite to `100 eps (1 + max|R|)`).
    """

    # Called through `equinox.filter_jit`, traced once each (`nhjax._user_function`).
    hamiltonian: Callable[[Float[Array, " N"], Any], Float[Array, ""]] = eqx.field(converter=traced_once)
    structure: Callable[[Float[Array, " N"], Any], Float[Array, "N N"]] = eqx.field(converter=traced_once)
    dissipation: Callable[[Float[Array, " N"], Any], Float[Array, "N N"]] | None = eqx.field(
        default=None, converter=traced_once
    )
    force: Callable[[Any, Float[Array, " N"], Any], Float[Array, " N"]] | None = eqx.field(
        default=None, converter=traced_once
    )

    def __check_init__(self):
        check_function("SkewGradientSystem", "hamiltonian", self.hamiltonian, "hamiltonian(x, args) -> scalar")
        check_function("SkewGradientSystem", "structure", self.structure, "structure(x, args) -> (N, N)")
        check_function("SkewGradientSystem", "dissipation", self.dissipation, "dissipation(x, args) -> (N, N)", optional=True)
        check_function("SkewGradientSystem", "force", self.force, "force(t, x, args) -> (N,)", optional=True)

    def gradient(self, x: Float[Array, " N"], args: Any) -> Float[Array, " N"]:
        return jax.grad(self.hamiltonian)(x, args)

    def field(self, t, y, args):
        gradient = self.gradient(y, args)
        field = self.structure(y, args) @ gradient
        applied = self.applied_force(t, y, args, gradient)
        return field if applied is None else field + applied

    def applied_force(self, t, x, args, gradient=None) -> Float[Array, " N"] | None:
        r"""$-R(x)\,
abla H + g(t, x)$, what the dissipation and the force add to the
        field, with $
abla H(x)$ or a method's discrete `gradient`; `None` for a
        conservative system."""
        if not self.is_forced():
            return None
        gradient = self.gradient(x, args) if gradient is None else gradient
        applied = jnp.zeros_like(gradient)
        if self.dissipation is not None:
            applied = applied - self.dissipation(x, args) @ gradient
        if self.force is not None:
            applied = applied + self.force(t, x, args)
        return applied

    def energy(self, y, args):
        return self.hamiltonian(y, args)

    def power(self, t, y, args):
        return self.power_along(t, y, self.gradient(y, args), args)

    def power_along(self, t, x, gradient, args) -> tuple[Float[Array, ""], Float[Array, ""]]:
        r"""(supplied, dissipated) $= (w^Tg(t, x),\ w^TR(x)w)$ for a gradient
        $w$: `power` at $w = \nabla H(x)$, and a method's discrete power at
        its discrete gradient (times the step, its `exchange`)."""
        zero = jnp.zeros((), gradient.dtype)
        supplied = zero if self.force is None else gradient @ self.force(t, x, args)
        dissipated = zero if self.dissipation is None else gradient @ self.dissipation(x, args) @ gradient
        return supplied, dissipated

    def check_shapes(self, y0, args):
        require_floating_vector("The state of a SkewGradientSystem", y0)
        (n,) = jnp.shape(y0)
        dtype = jnp.result_type(y0)
        converted = in_state_dtype(args, dtype)
        energy = jax.eval_shape(self.hamiltonian, y0, converted)
        require_scalar("hamiltonian(x, args)", energy)
        require_state_dtype("hamiltonian(x, args)", energy, dtype)
        structure = jax.eval_shape(self.structure, y0, converted)
        if structure.shape != (n, n):
            raise ValueError(
                f"structure(x, args) must return an ({n}, {n}) matrix for a state of "
                f"shape ({n},), got shape {structure.shape}."
            )
        require_state_dtype("structure(x, args)", structure, dtype)
        check_dissipation_and_force(self, (y0,), args, n, "x")

    def initial_state_result(self, y0, args):
        structure = self.structure(y0, args)
        dissipation_finite, dissipation = dissipation_at_start(self.dissipation, (y0,), args)
        evaluations_finite = (
            jnp.isfinite(self.hamiltonian(y0, args))
            & jnp.all(jnp.isfinite(self.gradient(y0, args)))
            & jnp.all(jnp.isfinite(structure))
            & dissipation_finite
        )
        asymmetry = jnp.max(jnp.abs(structure + structure.T))
        tolerance = 100 * jnp.finfo(structure.dtype).eps * (1 + jnp.max(jnp.abs(structure)))
        return first_failure(
            RESULTS.where(jnp.all(jnp.isfinite(y0)), RESULTS.successful, RESULTS.nonfinite_initial_state),
            RESULTS.where(evaluations_finite, RESULTS.successful, RESULTS.nonfinite_initial_evaluation),
            RESULTS.where(asymmetry <= tolerance, RESULTS.successful, RESULTS.structure_not_skew),
            dissipation,
        )
