r"""Adapted coordinates (§2.2): the structure (PiMat) and the momentum maps (ptransform).

With a frame $X(q) = (X_1, \dots, X_m)$ of $\mathcal{D}_q$ (columns, $n \times m$) and the
metric $g(q)$, the momenta on $\mathcal{D}^*$ are $\rho = X^T p$ (ptildetop) and, for
$p$ on $\mathcal{F}L(\mathcal{D})$, $p = g X (X^T g X)^{-1} \rho$ (ptoptilde).
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._linalg import solve_spd


def adapted_structure(
    frame: Float[Array, "n m"], bracket: Float[Array, "m m"]
) -> Float[Array, "n+m n+m"]:
    r"""$\Pi(q, \rho) = \begin{pmatrix} 0 & X \\ -X^T & -C^c_{ab}\rho_c \end{pmatrix}$,
    eq. (PiMat), from the frame $X$ and the skew block $-C^c_{ab}\rho_c$."""
    n = frame.shape[0]
    top = jnp.concatenate([jnp.zeros((n, n), frame.dtype), frame], axis=1)
    bottom = jnp.concatenate([-frame.T, bracket], axis=1)
    return jnp.concatenate([top, bottom], axis=0)


def momentum_to_adapted(frame, p):
    """rho = X^T p, eq. (ptildetop)."""
    return frame.T @ p


def adapted_to_momentum(frame, metric, rho):
    """p = g X (X^T g X)^{-1} rho, eq. (ptoptilde); X^T g X is symmetric positive
    definite (`nhjax._linalg.solve_spd`)."""
    return metric @ frame @ solve_spd(frame.T @ metric @ frame, rho)


def discrete_constraint_residual(constraints, qs: Float[Array, "T n"], args=None) -> Float[Array, "T-1 k"]:
    r"""$A(\bar q)(q_{k+1} - q_k)$, $\bar q = (q_k + q_{k+1})/2$, along saved positions
    `qs`: zero to roundoff for a discrete-gradient method with the midpoint structure,
    whose $q$-update $h X(\bar q) \partial\bar{\mathcal{H}}/\partial\rho$ lies in
    $\mathcal{D}_{\bar q}$ (§3.2, preservation of the nonholonomic constraints)."""
    midpoints = 0.5 * (qs[1:] + qs[:-1])
    return jax.vmap(lambda q, dq: constraints(q, args) @ dq)(midpoints, qs[1:] - qs[:-1])
