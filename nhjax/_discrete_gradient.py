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
result has lost six digits, and at $x' = x$ it is $0/0$. Newton's first iterate and
gradients flowing through the root find both sit in that regime. So when
$|x' - x|_\infty < \tau (1 + |\tfrac{x + x'}{2}|_\infty)$, with
$\tau = (4320\,\epsilon)^{1/5}$ ($\approx 4\cdot 10^{-3}$ in float64, $0.2$ in float32),
the divided difference is replaced by its two-point Gauss--Legendre quadrature,

$$\frac{f(b + \tfrac{1}{2}\delta) - f(b - \tfrac{1}{2}\delta)}{|\delta|}
  = \int_{-1/2}^{1/2} \nabla f(b + s\delta)\cdot\hat\delta \, ds
  \approx \tfrac12 \big[\nabla f(b + \tfrac{\delta}{2\sqrt3})
  + \nabla f(b - \tfrac{\delta}{2\sqrt3})\big]\cdot\hat\delta,$$

which needs only gradients (no cancellation, no division by $|\delta|$, and first-order
autodiff only) and is exact for $f$ of degree $\le 4$ along the segment. Its truncation
error, $\approx |f^{(5)}| |\delta|^5 / 4320$, is below the rounding error of the printed
formula at the switch, so (discGradEn) holds to roundoff on both sides of it, the value
is continuous there to roundoff, and at $x' = x$ the formula gives $\nabla f(x)$ exactly
with finite derivatives of every order.
"""

import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


ScalarFunction = Callable[[Float[Array, " N"], Any], Float[Array, ""]]

_GAUSS2_OFFSET = 0.5 / math.sqrt(3.0)


def _near_switch(dtype) -> float:
    """Relative size of $|x' - x|$ below which quadrature replaces the divided
    difference: where $|\\delta|^4/4320$ (quadrature) meets $\\epsilon/|\\delta|$
    (cancellation)."""
    return (4320.0 * float(jnp.finfo(dtype).eps)) ** 0.2


def _is_near(x, x1, delta):
    midpoint_scale = 1.0 + jnp.max(jnp.abs(0.5 * (x + x1)))
    return jnp.abs(delta) < _near_switch(x.dtype) * midpoint_scale


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
    second order. For nearly equal points the numerator is
    $\int_{-1/2}^{1/2} (\nabla f(\bar x + s\delta) - \nabla f(\bar x))\cdot\delta\, ds$,
    evaluated by two-point Gauss quadrature (see the module docstring).
    """
    delta = x1 - x
    midpoint = 0.5 * (x + x1)
    offset = _GAUSS2_OFFSET * delta
    grads = jax.vmap(jax.grad(f), in_axes=(0, None))(
        jnp.stack([midpoint, midpoint + offset, midpoint - offset]), args
    )
    grad_mid = grads[0]
    slope_mid = grad_mid @ delta
    printed = f(x1, args) - f(x, args) - slope_mid
    quadrature = 0.5 * (grads[1] + grads[2]) @ delta - slope_mid
    near = jnp.all(_is_near(x, x1, delta))
    numerator = jnp.where(near, quadrature, printed)
    delta_sq = delta @ delta
    safe_delta_sq = jnp.where(delta_sq == 0, 1.0, delta_sq)
    return grad_mid + (numerator / safe_delta_sq) * delta


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
