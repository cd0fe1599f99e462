"""What a system's functions compute from what, read from their JAX programs at trace
time: which methods may take the shortcuts a constant metric allows."""

import collections

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import ClosedJaxpr, Jaxpr, Var


# Primitives that apply a jaxpr to their operands one to one (a call, with its outputs
# the jaxpr's outputs): dependence can be traced through them exactly. Anything else
# that takes a dependent operand (loops, branches, linear solves) is taken to make every
# output dependent, which can only send a system down the general path.
_CALL_PRIMITIVES = frozenset(
    {
        "jit",
        "pjit",
        "closed_call",
        "core_call",
        "remat",
        "remat2",
        "checkpoint",
        "custom_jvp_call",
        "custom_vjp_call",
        "custom_vjp_call_jaxpr",
    }
)


def _called_jaxpr(eqn) -> Jaxpr | None:
    if eqn.primitive.name not in _CALL_PRIMITIVES:
        return None
    for name in ("jaxpr", "call_jaxpr", "fun_jaxpr"):
        inner = eqn.params.get(name)
        if isinstance(inner, ClosedJaxpr):
            inner = inner.jaxpr
        if (
            isinstance(inner, Jaxpr)
            and len(inner.invars) == len(eqn.invars)
            and len(inner.outvars) == len(eqn.outvars)
        ):
            return inner
    return None


def _dependent_outputs(jaxpr: Jaxpr, dependent_inputs: list[bool]) -> list[bool]:
    """Which outputs of `jaxpr` are computed from the inputs flagged in
    `dependent_inputs` (a forward sweep over its equations; conservative, see
    `_CALL_PRIMITIVES`)."""
    dependent = {var for var, flag in zip(jaxpr.invars, dependent_inputs) if flag}

    def flagged(atom):
        return isinstance(atom, Var) and atom in dependent

    for eqn in jaxpr.eqns:
        flags = [flagged(atom) for atom in eqn.invars]
        if not any(flags):
            continue
        inner = _called_jaxpr(eqn)
        out_flags = [True] * len(eqn.outvars) if inner is None else _dependent_outputs(inner, flags)
        dependent.update(var for var, flag in zip(eqn.outvars, out_flags) if flag)
    return [flagged(atom) for atom in jaxpr.outvars]


# Both answers are computed at trace time, and a run traces its step several times (and a
# program that integrates repeatedly, more): they are remembered per system, shapes and
# static arguments, as `jax.jit` remembers a trace. A system or static argument that
# cannot be hashed is analysed afresh every time.
_MEMO_SIZE = 256
_memo: collections.OrderedDict = collections.OrderedDict()


def _memoised(kind, compute, system, q, p, args):
    dynamic, static = eqx.partition(args, eqx.is_array)
    static_leaves, static_structure = jax.tree.flatten(static)
    inputs = jax.tree.leaves((q, p, dynamic))
    key = (
        kind,
        system,
        jax.tree.structure((q, p, dynamic)),
        tuple((jnp.shape(x), jnp.result_type(x)) for x in inputs),
        static_structure,
        tuple(static_leaves),
    )
    try:
        hash(key)
    except TypeError:
        return compute(system, q, p, args)
    if key in _memo:
        _memo.move_to_end(key)
        return _memo[key]
    value = _memo[key] = compute(system, q, p, args)
    if len(_memo) > _MEMO_SIZE:
        _memo.popitem(last=False)
    return value


def _velocity_program(system, q, p, args):
    r"""The jaxpr of $\partial H/\partial p$ in $(q, p, \text{array leaves of args})$,
    traced on shapes and dtypes only, and the function it traces."""
    dynamic, static = eqx.partition(args, eqx.is_array)
    shape = lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x))  # noqa: E731

    def velocity(q, p, dynamic):
        return system.velocity(q, p, eqx.combine(dynamic, static))

    closed = jax.make_jaxpr(velocity)(shape(q), shape(p), jax.tree.map(shape, dynamic))
    return closed.jaxpr, velocity, dynamic


def velocity_dependence(system, q, p, args) -> tuple[bool, bool]:
    r"""Whether $\partial H/\partial p$, as a JAX program in $(q, p, \text{args})$,
    computes anything from $q$, and whether from the array leaves of `args`. Not from
    $q$ means the metric is constant (and then $\partial H/\partial q$ does not depend
    on $p$, since $\partial_p\partial_q H = \partial_q\partial_p H = 0$); not from
    `args` either means it is a constant of the program (`evaluated_inverse_metric`).

    Decided at trace time from the jaxpr of `system.velocity` (`jax.make_jaxpr`, on
    shapes and dtypes only), by following which variables are computed from which
    inputs. The answer is structural: a metric that depends on $q$ only through terms
    that vanish (such as `0 * q[0]`) counts as $q$-dependent. Array leaves of `args` are
    inputs of the program, never constants (they may be traced or differentiated).
    """
    return _memoised("dependence", _velocity_dependence, system, q, p, args)


def _velocity_dependence(system, q, p, args) -> tuple[bool, bool]:
    jaxpr, _, _ = _velocity_program(system, q, p, args)
    p_inputs = len(jax.tree.leaves(p))
    args_inputs = len(jaxpr.invars) - 1 - p_inputs
    on_position = any(_dependent_outputs(jaxpr, [True] + [False] * (p_inputs + args_inputs)))
    on_args = any(_dependent_outputs(jaxpr, [False] * (1 + p_inputs) + [True] * args_inputs))
    return on_position, on_args


def velocity_depends_on_position(system, q, p, args) -> bool:
    """The first answer of `velocity_dependence`: whether the metric may vary with $q$."""
    return velocity_dependence(system, q, p, args)[0]


def evaluated_inverse_metric(system, q, p, args) -> np.ndarray:
    r"""$K = \partial^2H/\partial p^2$ as a NumPy array, for a system whose
    $\partial H/\partial p$ computes nothing from $q$ nor from the array leaves of
    `args` (`velocity_dependence`): a constant of the program, evaluated once, at
    trace time, with zeros in place of the inputs it does not read (as one compiled
    program: evaluated operation by operation, each would be compiled on its own)."""
    return _memoised("inverse metric", _evaluated_inverse_metric, system, q, p, args)


def _evaluated_inverse_metric(system, q, p, args) -> np.ndarray:
    _, velocity, dynamic = _velocity_program(system, q, p, args)
    zeros = lambda x: np.zeros(jnp.shape(x), jnp.result_type(x))  # noqa: E731
    inputs = (zeros(q), zeros(p), jax.tree.map(zeros, dynamic))
    # Compiled ahead of time and called on NumPy zeros: executed, not staged into the
    # program being traced.
    compiled = jax.jit(jax.jacfwd(velocity, argnums=1)).lower(*inputs).compile()
    return np.asarray(compiled(*inputs))
