r"""A system's functions ($H$, $A$, $D$, $F$, $L$), traced once per program.

A step of an nhjax method evaluates $H$ and $A$ at many points and differentiates them
in several ways (the velocity, the force, products with the metric, the frame and its
linearisation, the Gonzalez correction, the chord matrix): GONZALEZ-R's program for
Euler's disk calls its $H$ 33 times. Called as plain Python, each call traces the
user's code again: for the disk's $H$ from its mass matrix, tracing $H$ (and the
solve inside it) was about half of the time the run's trace took. Called through
`equinox.filter_jit`, the body is traced once per shape and static arguments, and each
further call, and each derivative of the same kind, reuses that trace: JAX caches a
traced function, and its forward, transposed and batched forms, by the function. XLA
inlines the calls, so the compiled program, and what it computes, are those of the
plain calls.
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx


class UserFunction(eqx.Module):
    """`function`, called through `equinox.filter_jit` (array leaves of the arguments
    traced, the other leaves static). Equal for equal functions, so two systems built
    from the same functions share compiled programs."""

    function: Callable

    def __call__(self, *arguments: Any, **keywords: Any) -> Any:
        return eqx.filter_jit(self.function)(*arguments, **keywords)


def traced_once(function: Callable | None) -> Callable | None:
    """`function` as a `UserFunction`; `None`, and what already traces its own body
    once (a `UserFunction`, or a module that wraps its own functions: `owns_tracing`),
    unchanged."""
    if function is None or isinstance(function, UserFunction) or getattr(function, "owns_tracing", False):
        return function
    return UserFunction(function)


def check_function(owner: str, name: str, value: Any, signature: str, optional: bool = False) -> None:
    """A `ValueError` naming `owner`'s `name` unless `value` (or the function a
    `UserFunction` wraps) is callable, or `None` where it is `optional`: a name or a
    number given for a function was taken and failed only when a run traced it."""
    function = value.function if isinstance(value, UserFunction) else value
    if (function is None and optional) or callable(function):
        return
    alternative = " or None" if optional else ""
    raise ValueError(f"{owner}: {name} must be a function {signature}{alternative}, got {function!r}.")
