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
result has lost six digits, and at $x' = x$ it is $0/0$. Newton's first iterates and
gradients flowing through the root find both visit that regime. So below a switch
$|x'_i - x_i| < \tau (1 + |\bar x_i|)$, $\bar x = \tfrac{x + x'}{2}$ (for every $i$,
in Gonzalez; per coordinate, in Itoh--Abe), where the truncation error
of a local expansion, $\approx |f^{(5)}||\delta|^5/C$, falls below the rounding error
$\epsilon|f|$ of the printed formula ($\tau = (C\epsilon)^{1/5}$, about $4\cdot10^{-3}$ in
float64 and $0.2$ in float32), each uses a form free of cancellation:

- Itoh--Abe: the divided difference along coordinate $i$ is the two-point
  Gauss--Legendre quadrature $\tfrac12[\partial_i f(b + \tfrac{\delta_i}{2\sqrt3}e_i)
  + \partial_i f(b - \tfrac{\delta_i}{2\sqrt3}e_i)]$ about the segment midpoint $b$
  ($C = 4320$): gradients only, no subtraction, no division.
- Gonzalez: the derivatives of the correction term by its Taylor expansion, its
  value still the printed one (see `gonzalez`, $C = 1920$).

(discGradEn) then holds to roundoff on both sides of the switch, values are continuous
across it to roundoff, and at $x' = x$ both give $\nabla f(x)$ exactly, with finite and
accurate derivatives, forward and reverse.
"""

import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._linalg import safe_norm


ScalarFunction = Callable[[Float[Array, " N"], Any], Float[Array, ""]]

_GAUSS2_OFFSET = 0.5 / math.sqrt(3.0)
# Truncation constants C of the local expansions: |f^(5)| |delta|^5 / C.
_GAUSS2_TRUNCATION = 4320.0
_TAYLOR_TRUNCATION = 1920.0


def _is_near(x, x1, delta, truncation: float):
    r"""Where $|\delta_i|$ is below the switch $\tau(1 + |\bar x_i|)$,
    $\tau = (C\epsilon)^{1/5}$: there the expansion's truncation error, $|\delta|^5/C$,
    is below the cancellation error $\epsilon$ of the printed divided difference.

    Each coordinate is measured against its own size: a scale common to all (such as
    $1 + |\bar x|_\infty$) would let one large coordinate, a position far from the
    origin, declare every step of the others "near", and the Taylor branch would then
    be used for increments it does not resolve."""
    switch = (truncation * float(jnp.finfo(x.dtype).eps)) ** 0.2
    return jnp.abs(delta) < switch * (1.0 + jnp.abs(0.5 * (x + x1)))


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
    xi, weights = np.polynomial.legendre.leggauss(nodes)
    xi = jnp.asarray(0.5 * (xi + 1.0), dtype=x.dtype)
    weights = jnp.asarray(0.5 * weights, dtype=x.dtype)
    points = x[None, :] + xi[:, None] * (x1 - x)[None, :]
    grads = jax.vmap(jax.grad(f), in_axes=(0, None))(points, args)
    return weights @ grads


def _third_directional_derivative(f, x, gradient, direction, args):
    r"""$D^3 f(x)[u, u, u]$ for $u$ = `direction`, given `gradient` $= \nabla f(x)$:
    the central second difference of the directional derivative
    $g(s) = Df(x + s\,Sv)[Sv]$ along $Sv$, $v = S^{-1}u/|S^{-1}u|$,
    $S = \mathrm{diag}(1 + |x_i|)$, at the step $\varepsilon = \epsilon^{1/4}$:
    $D^3f(x)[u, u, u] \approx |S^{-1}u|^3\,(g(\varepsilon) - 2g(0) + g(-\varepsilon))
    / \varepsilon^2$, with $g(0) = \nabla f(x)^T Sv$.

    Its relative error, $\varepsilon^2/12$ from truncation and $\epsilon/\varepsilon^2$
    from rounding, is about $\sqrt\epsilon$. Where it is used, in the correction term
    below the switch, the correction is $O(\tau^2)$ and the error it leaves in
    (discGradEn) is below $10^{-8}\tau^3 |D^3f| < \epsilon$. Nested forward-mode
    autodiff would be exact, but the derivatives of the step's root (implicit function
    theorem) would then need fourth derivatives of $f$: for GONZALEZ-R, through the QR
    factorisation, a graph that takes a minute to compile. The difference form needs
    only first derivatives, and second ones for gradients.
    """
    scale = jax.lax.stop_gradient(1.0 + jnp.abs(x))
    scaled = direction / scale
    length = safe_norm(scaled)
    unit = scaled / jnp.where(length == 0, 1.0, length)
    step = float(jnp.finfo(x.dtype).eps) ** 0.25
    along = scale * unit

    def slope(offset):
        return jax.jvp(lambda z: f(z, args), (x + offset * along,), (along,))[1]

    # One traced slope for both offsets: half the program, under every derivative.
    forward, backward = jax.vmap(slope)(jnp.array([step, -step], dtype=x.dtype))
    second_difference = forward - 2.0 * (gradient @ along) + backward
    return second_difference / step**2 * length**3


def gonzalez(
    f: ScalarFunction,
    x: Float[Array, " N"],
    x1: Float[Array, " N"],
    args: Any = None,
) -> Float[Array, " N"]:
    r"""Midpoint (Gonzalez) discrete gradient, eq. (gonzales):

    $$\bar\nabla_2 f(x, x') = \nabla f(\bar x)
      + \frac{f(x') - f(x) - \nabla f(\bar x)^T \delta}{|\delta|^2}\,\delta,
      \qquad \bar x = \tfrac{x + x'}{2},\ \delta = x' - x.$$

    Symmetric in $(x, x')$, so with a symmetric $\tilde\Pi$ the method (E-int) is
    second order.

    **Nearly equal points.** The coefficient of $\delta$ is a quantity of size
    $|\delta|$ obtained from differences of size $|\delta|$ (or $|f|$), so any formula
    that forms it by subtraction carries an error $\epsilon/|\delta|$ in the
    coefficient: harmless in the value, which multiplies it by $\delta$, but not in the
    derivative, which contains the coefficient itself. Below the switch (module
    docstring, here $\tau = (1920\epsilon)^{1/5}$) the correction's derivatives are
    therefore those of its Taylor expansion about $\bar x$,
    $\tfrac{1}{24} D^3 f(\bar x)[\hat\delta, \hat\delta, \hat\delta]\, |\delta|\,\delta
    + O(|\delta|^4)$, $\hat\delta = \delta/|\delta|$, with the third derivative from
    a second difference of directional derivatives at a fixed step (not one of size
    $|\delta|$, so no cancellation grows as $\delta \to 0$; see
    `_third_directional_derivative`), while its value stays the printed formula's
    (the expansion's at $\delta = 0$): the expansion's truncation error has one sign
    from step to step, and as a value it drifted GONZALEZ-R's energy by $3\cdot10^{-10}$
    over $2\cdot10^4$ steps of $h = 0.1/17$ on the gearbox, against $10^{-13}$ now.
    Both forms are evaluated and one selected (`jnp.where`), not branched on
    (`lax.cond`): every caller in nhjax that uses this form differentiates it (the
    derivatives of a step's root), and a derivative program through a `lax.cond`
    carries both branches' linearisations and their saved values, which made the
    reverse-mode program through a GONZALEZ-R run a quarter larger to compile; a step's
    values come from `gonzalez_values`, which has no Taylor form.
    """
    return gonzalez_correction(f, midpoint_gradient(f, x, x1, args), x, x1, args)


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
) -> Float[Array, " N"]:
    r"""The values of `gonzalez`, without its Taylor form for nearly equal points.

    `gonzalez` takes its value from the printed formula on both sides of the switch and
    uses the Taylor form only for its derivatives, so the two functions agree in value;
    this one has no branch, and under `vmap` no third derivative evaluated by every
    trajectory at every call. For a caller that never differentiates it: the chord
    iteration's residual (`nhjax.AbstractMethod.root_find_residual`)."""
    return gonzalez_correction(f, midpoint_gradient(f, x, x1, args), x, x1, args, taylor=False)


def gonzalez_correction(
    f: ScalarFunction,
    gradient: Float[Array, " N"],
    x: Float[Array, " N"],
    x1: Float[Array, " N"],
    args: Any = None,
    *,
    taylor: bool = True,
    f_x: Float[Array, ""] | None = None,
) -> Float[Array, " N"]:
    r"""$g + \frac{f(x') - f(x) - g^T\delta}{|\delta|^2}\delta$ for a given midpoint
    gradient $g$: (gonzales) when $g = \nabla f(\bar x)$. `f_x`: $f(x)$, if the caller
    has it (a root find evaluates this with one $x$ and many $x'$).

    (discGradEn) holds for any $g$. With `taylor=True`, $g$ must be $\nabla f(\bar x)$
    and nearly equal points use the Taylor form of `gonzalez` for the derivatives. With
    `taylor=False` the printed formula is used down to $\delta = 0$, where the value is
    $g$: the same values, with derivatives that lose accuracy as $\epsilon/|\delta|^2$
    for nearly equal points; for an approximate $g$ (GONZALEZ-R with finite
    differences, where no expansion applies) and for callers that never differentiate
    the result (`gonzalez_values`).
    """
    delta = x1 - x
    squared_length = delta @ delta
    zero = squared_length == 0
    numerator = f(x1, args) - (f(x, args) if f_x is None else f_x) - gradient @ delta
    printed = (numerator / jnp.where(zero, 1.0, squared_length)) * jnp.where(zero, 0.0, delta)
    if not taylor:
        return gradient + printed
    # A branch, not a select: the expansion's third derivative, and in derivative
    # programs its linearisation, run only for nearly equal points (under `vmap` a
    # batch still evaluates both, as a select would).
    near = jnp.all(_is_near(x, x1, delta, _TAYLOR_TRUNCATION))
    return gradient + jax.lax.cond(near, lambda: _taylor_form(f, gradient, x, x1, delta, printed, args), lambda: printed)


def _taylor_form(f, gradient, x, x1, delta, printed, args):
    """The correction term of `gonzalez_correction` for nearly equal points: the
    printed value, with the derivatives of its Taylor expansion."""
    length = safe_norm(delta)
    direction = delta / jnp.where(length == 0, 1.0, length)
    third = _third_directional_derivative(f, 0.5 * (x + x1), gradient, direction, args)
    expansion = (third * length / 24.0) * delta
    # The value is the printed formula's, the derivatives the expansion's: the
    # expansion's truncation error, though below the rounding of the printed formula at
    # the switch, has one sign step after step, and over 10^4 steps and more it would
    # drift the energy; the printed value keeps (discGradEn) to rounding, and its
    # cancellation, an error of eps |f| / |delta| in the gradient, moves the step by
    # rounding only (the step is h times it, and |delta| = O(h)).
    return expansion + jax.lax.stop_gradient(printed - expansion)


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
    (n,) = x.shape
    index = jnp.arange(n)
    from_new = index[None, :] < jnp.arange(n + 1)[:, None]
    corners = jnp.where(from_new, x1[None, :], x[None, :])
    values = jax.vmap(f, in_axes=(0, None))(corners, args)
    delta = x1 - x
    near = _is_near(x, x1, delta, _GAUSS2_TRUNCATION)
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
