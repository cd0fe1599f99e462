"""Reading and checking the examples' parameters."""

import math

import jax


def parameters(args, names: tuple[str, ...], example: str) -> tuple:
    """`args[name]` for each of `names`, or a `ValueError` saying what the example's
    functions need when `args` does not hold them (such as `args=None`)."""
    try:
        return tuple(args[name] for name in names)
    except (TypeError, KeyError, IndexError):
        raise ValueError(
            f"The {example}'s functions read the parameters {', '.join(names)} from "
            f"args: pass the example's .args (a dict with those keys), got args={args!r}."
        ) from None


def _number(example: str, name: str, value) -> float:
    """A concrete parameter as a float, or a `ValueError` naming it where it is not a
    real number (a string, even one that reads as a number; an array of several
    values)."""
    if not isinstance(value, (str, bytes)):
        try:
            return float(value)
        except (TypeError, ValueError):
            pass
    raise ValueError(f"The {example}'s {name} must be a real number, got {name}={value!r}.")


def require_positive(example: str, **values) -> None:
    """A `ValueError` for a concrete parameter that is not positive and finite (traced
    ones are left to the initial-state checks of `nhjax.integrate`)."""
    for name, value in values.items():
        if isinstance(value, jax.core.Tracer):
            continue
        number = _number(example, name, value)
        if not (math.isfinite(number) and number > 0):
            raise ValueError(f"The {example}'s {name} must be positive and finite, got {name}={value}.")


def require_finite(example: str, **values) -> None:
    """A `ValueError` for a concrete parameter that is not finite."""
    for name, value in values.items():
        if not isinstance(value, jax.core.Tracer) and not math.isfinite(_number(example, name, value)):
            raise ValueError(f"The {example}'s {name} must be finite, got {name}={value}.")


def require_non_negative(example: str, **values) -> None:
    """A `ValueError` for a concrete parameter that is negative or not finite."""
    require_finite(example, **values)
    for name, value in values.items():
        if not isinstance(value, jax.core.Tracer) and float(value) < 0:
            raise ValueError(f"The {example}'s {name} must not be negative, got {name}={value}.")


def is_concrete_zero(value) -> bool:
    """Whether `value` is known to be 0 when a system is built (a traced value is not):
    a friction or resistance that is, leaves the system conservative."""
    return not isinstance(value, jax.core.Tracer) and float(value) == 0.0
