r"""Discrete gradients (paper §3.1, Definition 3.1).

A discrete gradient of $f: \mathbb{R}^N \to \mathbb{R}$ is a continuous map
$\bar\nabla f(x, x')$ with

$$\bar\nabla f(x, x')^T (x' - x) = f(x') - f(x) \qquad \text{(discGradEn)}$$
$$\bar\nabla f(x, x) = \nabla f(x) \qquad \text{(discGradCons)}$$

All three share one signature, `dg(f, x, x1, args) -> array shaped like x`, where
`f(x, args)` returns a scalar; every derivative of `f` comes from autodiff.

**Nearly equal points.** Gonzalez (gonzales) and Itoh--Abe (itoAbe) divide a
difference of `f` by $|x' - x|$. Evaluated as printed, the rounding error of that
difference, $\epsilon |f|$, is amplified by $1/|x' - x|$: at $|x' - x| = 10^{-10}$ the
result has lost six digits, and at $x' = x$ it is $0/0$. Small motions (near an
equilibrium, or a body nearly at rest), Newton's first iterates and gradients flowing
through the root find all visit that regime. So below a switch
$|x'_i - x_i| < \tau (1 + |\bar x_i|)$, $\bar x = \tfrac{x + x'}{2}$ (for every $i$,
in Gonzalez; per coordinate, in Itoh--Abe), where the truncation error of the two-point
Gauss--Legendre rule, $\approx |f^{(5)}||\delta|^5/4320$, falls below the rounding error
$\epsilon|f|$ of the printed formula ($\tau = (4320\epsilon)^{1/5}$, about
$4\cdot10^{-3}$ in float64 and $0.2$ in float32), each takes the difference of `f`
from gradients along the segment instead: no subtraction of values, and for Itoh--Abe
no division.

(discGradEn) then holds to the rounding of $f(x') - f(x)$ on both sides of the switch,
values are continuous across it to roundoff, and at $x' = x$ both give $\nabla f(x)$
exactly, with finite and accurate derivatives.
"""

import functools
import math
from collections.abc import Callable
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._linalg import safe_norm
from ._rare_branch import rarely
from ._system import require_floating_vector
from ._tangents import split_by_tangents


ScalarFunction = Callable[[Float[Array, " N"], Any], Float[Array, ""]]

_GAUSS2_OFFSET = 0.5 / math.sqrt(3.0)
# The truncation constant C of the two-point Gauss rule: |f^(5)| |delta|^5 / C.
_GAUSS2_TRUNCATION = 4320.0


def _is_near(x, x1, delta):
    r"""Where $|\delta_i|$ is below the switch $\tau(1 + |\bar x_i|)$,
    $\tau = (4320\epsilon)^{1/5}$: there the two-point Gauss rule's truncation error,
    $|\delta|^5/4320$, is below the cancellation error $\epsilon$ of the printed
    divided difference.

    Each coordinate is measured against its own size: a scale common to all (such as
    $1 + |\bar x|_\infty$) would let one large coordinate, a position far from the
    origin, declare every step of the others "near", and the quadrature would then be
    used for increments it does not resolve."""
    switch = (_GAUSS2_TRUNCATION * float(jnp.finfo(x.dtype).eps)) ** 0.2
    return jnp.abs(delta) < switch * (1.0 + jnp.abs(0.5 * (x + x1)))


def check_points(name: str, x, x1) -> None:
    """A `ValueError` naming `name` unless `x` and `x1` are two points of one space,
    floating-point vectors of one shape: what every discrete gradient here differences,
    and every structure approximation (`nhjax.midpoint_structure`) averages. Checked
    on shapes and dtypes only, when a function is traced."""
    require_floating_vector(f"{name}'s x", x)
    require_floating_vector(f"{name}'s x1", x1)
    if jnp.shape(x) != jnp.shape(x1):
        raise ValueError(f"{name} takes two points of one shape, got shapes {jnp.shape(x)} and {jnp.shape(x1)}.")


def avf(
    f: ScalarFunction,
    x: Float[Array, " N"],
    x1: Float[Array, " N"],
    args: Any = None,
    *,
    nodes: int = 8,
) -> Float[Array, " N"]:
    r"""Averaged vector field (mean value) discrete gradient, eq. (AVF):
    $\bar\nabla_1 f(x, x') = \int_0^1 \nabla f((1 - \xi) x + \xi x')\, d\xi$.

    The integral is computed by Gauss--Legendre quadrature with `nodes` nodes, which is
    exact for $f$ polynomial of degree $\le 2\,$`nodes` along the segment; for other $f$
    (discGradEn) holds up to the quadrature error, $O(|x' - x|^{2\,\mathrm{nodes}+1})$.
    The default of 8 nodes keeps that error below float64 roundoff for smooth $f$ and
    $|x' - x| \lesssim 1$. Choose another count with `functools.partial(avf, nodes=k)`.
    """
    if nodes < 1:
        raise ValueError(f"avf needs at least one quadrature node, got nodes={nodes}")
    check_points("avf", x, x1)
    xi, weights = np.polynomial.legendre.leggauss(nodes)
    xi = jnp.asarray(0.5 * (xi + 1.0), dtype=x.dtype)
    weights = jnp.asarray(0.5 * weights, dtype=x.dtype)
    points = x[None, :] + xi[:, None] * (x1 - x)[None, :]
    grads = jax.vmap(jax.grad(f), in_axes=(0, None))(points, args)
    return weights @ grads


@eqx.filter_custom_jvp
def _third_directional_derivative(f, x, direction, args):
    r"""$D^3 f(x)[u, u, u]$ for $u$ = `direction`: the central third difference of the
    values $\phi(s) = f(x + s\,Sv)$ along $Sv$, $v = S^{-1}u/|S^{-1}u|$,
    $S = \mathrm{diag}(1 + |x_i|)$, at the step $\varepsilon = \epsilon^{1/5}$:
    $$D^3f(x)[u, u, u] \approx |S^{-1}u|^3\,
      \frac{\phi(2\varepsilon) - 2\phi(\varepsilon) + 2\phi(-\varepsilon) - \phi(-2\varepsilon)}
           {2\varepsilon^3}.$$

    It gives only derivatives (of the correction term below the switch,
    `gonzalez_correction`), never values, so it leaves (discGradEn) as it is. Its
    derivative in $x$, $u$ and the arguments is the same difference of first
    derivatives of $f$, in error by $\varepsilon^2|D^6f|/4$ from truncation and
    $3\epsilon|Df|/\varepsilon^3$ from rounding, each about $10^{-6}$ where the
    derivatives of $f$ are of size 1 in units of $S$ (and
    $3D^3f[u, u, \cdot]$, its derivative in $u$, to $5\varepsilon^2|D^5f|/4$): the
    correction term it multiplies by $|\delta|\delta/24$ carries it into the step's
    Jacobian below $10^{-10}$. Nested autodiff would be exact, but the derivatives of the
    step's root (implicit function theorem) would then need fourth derivatives of $f$,
    and a difference of directional derivatives second ones: for GONZALEZ-R both go
    through the QR factorisation, in every derivative program, where they were about an
    eighth of the sleigh's and the disk's reverse-mode programs (`benchmarks/gradients.py`)
    though the branch runs only for nearly equal points. Values need no derivative of
    $f$ at all, and their derivatives first ones.

    Its derivative comes from one reverse pass through the four values
    (`_third_directional_derivative_jvp`), whatever the number of tangents.
    """
    return _third_difference(f, x, direction, args)


@_third_directional_derivative.def_jvp
def _third_directional_derivative_jvp(primals, tangents):
    r"""The derivative of `_third_directional_derivative` along `tangents`: its gradient
    in what has a tangent (the point, the direction, the arguments and the arrays of
    $f$), by one reverse pass, contracted with the tangents.

    The Jacobians that derivatives of a step form pull a batch of cotangents back
    through the residual (`nhjax._solver.base._linearised`), or push a batch of
    tangents through it; autodiff through the four values would hold arrays of the
    four points for every one of them, which takes XLA:CPU's
    step programs off sequential execution (`nhjax._linalg.SEQUENTIAL_BYTES`) even
    though this branch runs only for nearly equal points. The gradient depends on the
    primals alone, so a batch forms it once."""
    varying, fixed, given = split_by_tangents(primals, tangents)
    value, pullback = jax.vjp(lambda v: _third_difference(*eqx.combine(v, fixed)), varying)
    (gradient,) = pullback(jnp.ones_like(value))
    along = [
        jnp.sum(g * t.astype(g.dtype))
        for g, t in zip(jax.tree.leaves(gradient), jax.tree.leaves(given), strict=True)
    ]
    return value, sum(along, jnp.zeros_like(value))


def _third_difference(f, x, direction, args):
    """`_third_directional_derivative`'s value, differentiated by autodiff."""
    scale = jax.lax.stop_gradient(1.0 + jnp.abs(x))
    scaled = direction / scale
    length = safe_norm(scaled)
    unit = scaled / jnp.where(length == 0, 1.0, length)
    step = float(jnp.finfo(x.dtype).eps) ** 0.2
    along = scale * unit
    # One traced f for the four offsets.
    offsets = step * jnp.array([2.0, 1.0, -1.0, -2.0], dtype=x.dtype)
    values = jax.vmap(lambda offset: f(x + offset * along, args))(offsets)
    third_difference = values @ jnp.array([1.0, -2.0, 2.0, -1.0], dtype=x.dtype)
    return third_difference / (2.0 * step**3) * length**3


def gonzalez(
    f: ScalarFunction,
    x: Float[Array, " N"],
    x1: Float[Array, " N"],
    args: Any = None,
    *,
    f_x: Float[Array, ""] | None = None,
) -> Float[Array, " N"]:
    r"""Midpoint (Gonzalez) discrete gradient, eq. (gonzales):

    $$\bar\nabla_2 f(x, x') = \nabla f(\bar x)
      + \frac{f(x') - f(x) - \nabla f(\bar x)^T \delta}{|\delta|^2}\,\delta,
      \qquad \bar x = \tfrac{x + x'}{2},\ \delta = x' - x.$$

    Symmetric in $(x, x')$, so with a symmetric $\tilde\Pi$ the method (E-int) is
    second order.

    **Nearly equal points.** The difference $f(x') - f(x)$, computed from the two
    values, carries their rounding, $\epsilon|f|$, which the correction term divides by
    $|\delta|$: an error of $\epsilon|f|/|\delta|$ in the gradient. Near an equilibrium
    of a system whose energy is far from zero (a pendulum at rest at its lowest point,
    $|f| \approx 1$, moving by $|\delta| = 10^{-13}$ per step) that is $10^{-3}$ against a
    gradient of $10^{-12}$: the step's equations are noise, and no root finder solves
    them. Below the switch of the module docstring (here $C = 4320$, for every
    coordinate) the difference is therefore the two-point Gauss--Legendre quadrature of
    $\nabla f$ along the segment (`segment_difference`), whose error is that of the
    gradients, $\epsilon|\nabla f||\delta|$, plus a truncation $|\delta|^5/4320$ in
    units where the derivatives are of size 1; it is taken where it agrees with the
    difference of the values to four of their roundings, $\epsilon(|f(x)| + |f(x')|)$,
    which it does wherever the motion is too small for the values to resolve it, and
    the difference of the values elsewhere (a function periodic in an angle wound far
    from the origin has derivatives far above 1 in those units). The value and the
    derivatives come from the form selected: (discGradEn) holds to a few roundings of
    $f(x') - f(x)$ on both sides of the switch, and at $x' = x$ the result is
    $\nabla f(x)$ exactly, with finite and accurate derivatives.

    The form is selected by a branch (`lax.cond`), not a select: the quadrature's two
    gradients, and in derivative programs their linearisation, run only for nearly
    equal points (under `vmap` a batch evaluates both, as a select would; the methods'
    root finds, which never differentiate, use `gonzalez_values`, which keeps the
    quadrature to the steps where some trajectory needs it).

    `f_x`: $f(x)$, where the caller has it (a method's residual, evaluated at many $x'$
    from one $x$, computes it once a step), else computed here.
    """
    check_points("gonzalez", x, x1)
    return gonzalez_correction(f, midpoint_gradient(f, x, x1, args), x, x1, args, f_x=f_x)


def midpoint_gradient(
    f: ScalarFunction,
    x: Float[Array, " N"],
    x1: Float[Array, " N"],
    args: Any = None,
) -> Float[Array, " N"]:
    r"""$\nabla f(\tfrac{x + x'}{2})$: the Gonzalez discrete gradient without its
    correction term. Not a discrete gradient ((discGradEn) fails at $O(|\delta|^3)$);
    a method's simplified residual uses it for the chord matrix (see
    `nhjax._solver.chord`)."""
    return jax.grad(f)(0.5 * (x + x1), args)


def gonzalez_values(
    f: ScalarFunction,
    x: Float[Array, " N"],
    x1: Float[Array, " N"],
    args: Any = None,
    *,
    f_x: Float[Array, ""] | None = None,
) -> Float[Array, " N"]:
    r"""The values of `gonzalez`, for a caller that never differentiates them (the
    chord iteration's residual, `nhjax.AbstractMethod.root_find_residual`): the same
    forms on the same sides of the switch, with the quadrature selected by `rarely`, so
    that under `vmap` a batch evaluates it only at the calls where some trajectory has
    nearly equal points. Not differentiable. `f_x` as for `gonzalez`."""
    return gonzalez_correction(f, midpoint_gradient(f, x, x1, args), x, x1, args, branch="rarely", f_x=f_x)


def with_start_value(discrete_gradient: Callable, f_x: Float[Array, ""] | None) -> Callable:
    """`discrete_gradient` with $f(x)$ given (`f_x`) where it is `gonzalez` or
    `gonzalez_values`, which take it; any other discrete gradient unchanged. A method's
    residual, evaluated at many $x'$ from one $x$, computes $f(x)$ once a step."""
    if discrete_gradient in (gonzalez, gonzalez_values):
        return functools.partial(discrete_gradient, f_x=f_x)
    return discrete_gradient


def segment_difference(
    gradient: Callable[[Float[Array, " N"], Any], Float[Array, " N"]],
    x: Float[Array, " N"],
    x1: Float[Array, " N"],
    args: Any = None,
) -> Float[Array, ""]:
    r"""$f(x') - f(x) = \int_0^1 \nabla f(x + \xi\delta)^T\delta\,d\xi$ by the two-point
    Gauss--Legendre rule, $\tfrac12[\nabla f(\bar x + \tfrac{\delta}{2\sqrt3})
    + \nabla f(\bar x - \tfrac{\delta}{2\sqrt3})]^T\delta$, from
    `gradient(z, args)` $= \nabla f(z)$: exact for $f$ polynomial of degree 4 along the
    segment, with truncation $|D^5f[\delta, \ldots, \delta]|/4320$ otherwise, and free
    of the cancellation of $f(x') - f(x)$ (its rounding is $\epsilon|\nabla f||\delta|$)."""
    delta = x1 - x
    middle = 0.5 * (x + x1)
    offset = _GAUSS2_OFFSET * delta
    gradients = jax.vmap(gradient, in_axes=(0, None))(jnp.stack([middle + offset, middle - offset]), args)
    return 0.5 * (gradients[0] + gradients[1]) @ delta


class Gradient(eqx.Module):
    """$\\nabla f$ as a callable pytree, `Gradient(f)(x, args)`: `f`'s arrays (a bound
    method's module) are leaves, so that it can be handed to a branch as an operand."""

    f: ScalarFunction

    def __call__(self, x, args):
        return jax.grad(self.f)(x, args)


Branch = Literal["cond", "rarely"]


# How far, in roundings of the two values, the quadrature may stray from the printed
# difference and still be taken: beyond that its truncation shows.
_AGREEMENT = 4.0


def _validated_difference(operands):
    r"""The quadrature's difference (`segment_difference`) where it agrees with the
    printed one to `_AGREEMENT` times the printed one's rounding, $\epsilon(|f(x)| +
    |f(x')|)$; the printed one where it does not, which is where the quadrature's
    truncation is above rounding (the switch of `_is_near` assumes derivatives of
    size 1 in units of $1 + |x_i|$, which fails for a function periodic in a coordinate
    far from the origin, such as an angle wound up over a long run), or where that
    rounding estimate is too low (terms of $f$ that nearly cancel)."""
    gradient, x, x1, args, printed, rounding = operands
    difference = segment_difference(gradient, x, x1, args)
    return jnp.where(jnp.abs(difference - printed) <= _AGREEMENT * rounding, difference, printed)


def _difference_operands(f, x, x1, args, f_x, f_x1, segment):
    """What $f(x') - f(x)$ is taken from (`value_difference`, `gonzalez_correction`): the
    values' difference, the operands of `_validated_difference`, and whether the points
    are nearly equal (`_is_near`)."""
    f_x = f(x, args) if f_x is None else f_x
    f_x1 = f(x1, args) if f_x1 is None else f_x1
    printed = f_x1 - f_x
    rounding = jax.lax.stop_gradient(float(jnp.finfo(x.dtype).eps) * (jnp.abs(f_x) + jnp.abs(f_x1)))
    operands = ((Gradient(f), x, x1) if segment is None else segment) + (args, printed, rounding)
    return printed, operands, jnp.all(_is_near(x, x1, x1 - x))


def value_difference(
    f: ScalarFunction,
    x: Float[Array, " N"],
    x1: Float[Array, " N"],
    args: Any = None,
    *,
    branch: Branch = "cond",
    f_x: Float[Array, ""] | None = None,
    f_x1: Float[Array, ""] | None = None,
    segment: tuple | None = None,
) -> Float[Array, ""]:
    r"""$D = f(x') - f(x)$ as `gonzalez_correction` takes it: the difference of the
    values (`f_x`, `f_x1`, computed here where not given) or, for nearly equal points,
    `segment_difference(*segment, args)` where it agrees with the values' difference
    to a few roundings (`_validated_difference`). `branch` as there; the derivatives
    are those of the selected form."""
    printed, operands, near = _difference_operands(f, x, x1, args, f_x, f_x1, segment)
    if branch == "rarely":
        return rarely(near, _validated_difference, printed, operands)
    return jax.lax.cond(near, lambda: _validated_difference(operands), lambda: printed)


def gonzalez_correction(
    f: ScalarFunction,
    gradient: Float[Array, " N"],
    x: Float[Array, " N"],
    x1: Float[Array, " N"],
    args: Any = None,
    *,
    branch: Branch = "cond",
    taylor: bool = True,
    f_x: Float[Array, ""] | None = None,
    f_x1: Float[Array, ""] | None = None,
    segment: tuple | None = None,
) -> Float[Array, " N"]:
    r"""$g + \frac{D - g^T\delta}{|\delta|^2}\delta$ for a given midpoint gradient $g$,
    with $D = f(x') - f(x)$: (gonzales) when $g = \nabla f(\bar x)$; (discGradEn),
    $\bar\nabla f^T\delta = D$, holds for any $g$.

    $D$ is the difference of the values `f_x1 - f_x` (each computed here where not
    given) or, for nearly equal points, `segment_difference(*segment, args)` (by
    default `segment = (Gradient(f), x, x1)`) where it agrees with the values'
    difference to a few roundings (`_validated_difference`), as `gonzalez` describes.

    `branch`: `"cond"` (differentiable) or `"rarely"` (values only,
    `nhjax._rare_branch`). With `"cond"` and `taylor=True` ($g$ must
    then be $\nabla f(\bar x)$), for nearly equal points the correction's
    derivatives are those of its Taylor expansion about $\bar x$,
    $\tfrac{1}{24}D^3f(\bar x)[\hat\delta, \hat\delta, \hat\delta]|\delta|\delta$
    (`_third_directional_derivative`), its value the selected difference's: the
    quadrature's own derivative forms the coefficient $(D - g^T\delta)/|\delta|^2$
    from gradients $|\delta|$ apart, an error of $\epsilon|\nabla f|/|\delta|$ in the
    discrete gradient's Jacobian ($10^{-6}$ at $|\delta| = 10^{-10}$), and the values'
    difference, where it is selected, from values whose rounding is divided by
    $|\delta|^2$. Below the switch the expansion's truncation is the smaller error,
    by the choice of $\tau$. With `taylor=False` (an approximate $g$, GONZALEZ-R with
    finite differences) the derivatives are the selected form's own.
    """
    delta = x1 - x
    squared_length = delta @ delta
    zero = squared_length == 0
    printed, operands, near = _difference_operands(f, x, x1, args, f_x, f_x1, segment)

    def correction(difference):
        numerator = difference - gradient @ delta
        return (numerator / jnp.where(zero, 1.0, squared_length)) * jnp.where(zero, 0.0, delta)

    if branch == "rarely":
        return gradient + correction(rarely(near, _validated_difference, printed, operands))

    def near_correction():
        value = correction(_validated_difference(operands))
        if not taylor:
            return value
        length = safe_norm(delta)
        direction = delta / jnp.where(length == 0, 1.0, length)
        third = _third_directional_derivative(f, 0.5 * (x + x1), direction, args)
        expansion = (third * length / 24.0) * delta
        return expansion + jax.lax.stop_gradient(value - expansion)

    return gradient + jax.lax.cond(near, near_correction, lambda: correction(printed))


def itoh_abe(
    f: ScalarFunction,
    x: Float[Array, " N"],
    x1: Float[Array, " N"],
    args: Any = None,
) -> Float[Array, " N"]:
    r"""Coordinate increment (Itoh--Abe) discrete gradient, eq. (itoAbe):

    $$\bar\nabla_3 f(x, x')_i = \frac{f(y_i) - f(y_{i-1})}{x'_i - x_i},\qquad
      y_i = (x'_1, \dots, x'_i, x_{i+1}, \dots, x_N),$$

    and $\partial_i f(y_{i-1})$ when $x'_i = x_i$. It is not symmetric in $(x, x')$, so
    the method (E-int) built on it is first order only. For nearly equal coordinates the
    divided difference is the two-point Gauss quadrature of $\partial_i f$ along the
    coordinate segment (see the module docstring).
    """
    check_points("itoh_abe", x, x1)
    (n,) = x.shape
    index = jnp.arange(n)
    from_new = index[None, :] < jnp.arange(n + 1)[:, None]
    corners = jnp.where(from_new, x1[None, :], x[None, :])
    values = jax.vmap(f, in_axes=(0, None))(corners, args)
    delta = x1 - x
    near = _is_near(x, x1, delta)
    printed = (values[1:] - values[:-1]) / jnp.where(near, 1.0, delta)

    segment_midpoints = corners[:-1].at[index, index].set(0.5 * (x + x1))
    offset = _GAUSS2_OFFSET * delta
    unit = jnp.eye(n, dtype=x.dtype)

    def partial(point, direction):
        return jax.jvp(lambda p: f(p, args), (point,), (direction,))[1]

    upper = segment_midpoints.at[index, index].add(offset)
    lower = segment_midpoints.at[index, index].add(-offset)
    quadrature = 0.5 * (
        jax.vmap(partial)(upper, unit) + jax.vmap(partial)(lower, unit)
    )
    return jnp.where(near, quadrature, printed)


class SwappedArguments(eqx.Module):
    r"""`function` with its two points swapped: `SwappedArguments(dg)(f, x, x1, args)
    = dg(f, x1, x, args)`. Applied to a discrete gradient it gives another,
    $\bar\nabla f(x', x)$ (both (discGradEn) and (discGradCons) are symmetric in the
    two points); applied to a structure approximation $\tilde\Pi(x, x')$, likewise.
    This is how the adjoint of a discrete-gradient method is built."""

    function: Callable

    def __call__(self, f, x, x1, args=None):
        return self.function(f, x1, x, args)


def swap_arguments(function: Callable) -> Callable:
    """`SwappedArguments(function)`, or the original function when `function` is itself
    swapped."""
    if isinstance(function, SwappedArguments):
        return function.function
    return SwappedArguments(function)
