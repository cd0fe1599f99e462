"""The primals of a custom JVP split by whether they have a tangent."""

import equinox as eqx
import jax
from jaxtyping import PyTree


def _is_none(tangent) -> bool:
    return tangent is None


def split_by_tangents(primals: PyTree, tangents: PyTree) -> tuple[PyTree, PyTree, PyTree]:
    """`(varying, fixed, given)`: the primals that have a tangent (`equinox`'s
    `filter_custom_jvp` passes `None` for those that do not) and the rest, as
    `equinox.partition` splits them (`equinox.combine(varying, fixed)` is `primals`),
    and the tangents of `varying`, in its structure.

    A rule that linearises or pulls back only through `varying` does not
    differentiate with respect to what stays fixed: the arrays of a closure, the
    parameters a caller does not differentiate."""
    differentiated = jax.tree.map(lambda t: t is not None, tangents, is_leaf=_is_none)
    varying, fixed = eqx.partition(primals, differentiated)
    return varying, fixed, eqx.filter(tangents, differentiated, is_leaf=_is_none)
