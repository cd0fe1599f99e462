r"""Coefficients of collocation at the Gauss--Legendre nodes, with a quadrature of its
own along the collocation polynomial (`nhjax.EnergyPreservingCollocation`).

Notation: $s$ stages at the nodes $c_i$ (the zeros of the shifted Legendre polynomial
of degree $s$) with weights $b_i$ and Lagrange polynomials $\ell_i$; $r$ quadrature
nodes $\sigma_l$ with weights $w_l$ (the $r$-point Gauss rule on $[0, 1]$). With the
increments $Z_j = hK_j$, $K_j = \dot u(t_0 + c_jh)$, the collocation polynomial $u$ of
degree $s$ is $u(t_0 + \tau h) = x_0 + \sum_j\alpha_j(\tau)Z_j$,
$\alpha_j(\tau) = \int_0^\tau\ell_j$.
"""

import functools
from typing import NamedTuple

import numpy as np
from numpy.polynomial import legendre, polynomial


class CollocationTableau(NamedTuple):
    r"""The constants of one step, as NumPy arrays (compile-time constants):

    - `c`, `b`: the $s$ nodes and weights;
    - `a`: $a_{ij} = \alpha_j(c_i)$, the stage values $U_i = x_0 + \sum_ja_{ij}Z_j$
      (the Gauss method's Butcher matrix);
    - `quadrature_points`: $\alpha_j(\sigma_l)$, shape $(r, s)$, the points
      $u(t_0 + \sigma_lh)$ of the quadrature;
    - `quadrature_weights`: $w_l\ell_i(\sigma_l)/b_i$, shape $(s, r)$, so that
      $\sum_l$ of it times $g(\sigma_l)$ is the quadrature of
      $\int_0^1\ell_i(\tau)g(\tau)\,d\tau/b_i$;
    - `lagrange`: the coefficients of $\ell_j$, shape $(s, s)$, lowest degree first,
      to extrapolate $\dot u$ beyond the step;
    - `eigenvalues`, `eigenvectors`: $a = V\Lambda V^{-1}$ (complex; the Gauss
      method's $a$ has no real eigenvalue for even $s$ and one for odd $s$), and
      `eigenvectors_inverse`, $V^{-1}$: the simplified-Newton matrix
      $I - h\,a \otimes F$ is $(V \otimes I)(I - h\Lambda \otimes F)(V^{-1} \otimes I)$,
      inverted by $N \times N$ blocks (Hairer & Wanner, *Solving ODEs II*, §IV.8).
    """

    c: np.ndarray
    b: np.ndarray
    a: np.ndarray
    quadrature_points: np.ndarray
    quadrature_weights: np.ndarray
    lagrange: np.ndarray
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    eigenvectors_inverse: np.ndarray

    @property
    def stages(self) -> int:
        return self.c.shape[0]

    def inverse_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        r"""What the inverse of $I - h\,a \otimes F$ needs, by the eigenvalues of $a$:
        the eigenvalues $\mu_d$ whose blocks $B_d = (I - h\mu_dF)^{-1}$ are inverted (one
        per real eigenvalue or conjugate pair: a partner's block is the conjugate), and
        real weights $C$ of shape $(s, s, 2D)$, $D$ the number of blocks, such that the
        inverse's block $(i, j)$ is
        $\sum_d C_{ijd}\,\mathrm{Re}B_d + C_{ij(d + D)}\,\mathrm{Im}B_d$, that is
        $\mathrm{Re}(V_{ik}V^{-1}_{kj}B_k)$ summed over $k$, with
        $\mathrm{Re}(P\bar B) = \mathrm{Re}P\,\mathrm{Re}B + \mathrm{Im}P\,\mathrm{Im}B$
        for a partner's block."""
        inverted, source = [], []
        for eigenvalue in self.eigenvalues:
            partner = next(
                (d for d, other in enumerate(inverted) if np.isclose(other, eigenvalue.conjugate())), None
            )
            if partner is None or eigenvalue.imag == 0:
                source.append((len(inverted), 1.0))
                inverted.append(eigenvalue)
            else:
                source.append((partner, -1.0))
        count = len(inverted)
        weights = np.zeros((self.stages, self.stages, 2 * count))
        for k, (d, sign) in enumerate(source):
            product = np.outer(self.eigenvectors[:, k], self.eigenvectors_inverse[k, :])
            weights[:, :, d] += product.real
            weights[:, :, count + d] -= sign * product.imag
        return np.array(inverted), weights

    @property
    def shares_nodes(self) -> bool:
        """Whether the quadrature nodes are the collocation nodes ($r = s$): the
        quadrature's gradients are then those at the stage values."""
        return self.quadrature_points.shape[0] == self.stages


def gauss_legendre(points: int) -> tuple[np.ndarray, np.ndarray]:
    """The nodes and weights of the `points`-point Gauss rule on [0, 1]."""
    nodes, weights = legendre.leggauss(points)
    return (nodes + 1) / 2, weights / 2


@functools.cache
def collocation_tableau(stages: int, quadrature_nodes: int) -> CollocationTableau:
    """The `CollocationTableau` of `stages` Gauss nodes and a `quadrature_nodes`-point
    Gauss rule."""
    c, b = gauss_legendre(stages)
    sigma, w = gauss_legendre(quadrature_nodes)
    lagrange = []
    for i in range(stages):
        others = np.delete(c, i)
        lagrange.append(polynomial.polyfromroots(others) / np.prod(c[i] - others))
    lagrange = np.array(lagrange).reshape(stages, stages)
    integrals = [polynomial.polyint(coefficients) for coefficients in lagrange]
    a = np.array([[polynomial.polyval(c[i], integrals[j]) for j in range(stages)] for i in range(stages)])
    points = np.array([[polynomial.polyval(s, integrals[j]) for j in range(stages)] for s in sigma])
    weights = np.array([[w[l] * polynomial.polyval(sigma[l], lagrange[i]) / b[i] for l in range(quadrature_nodes)]
                        for i in range(stages)])
    eigenvalues, eigenvectors = np.linalg.eig(a)
    return CollocationTableau(
        c, b, a, points, weights, lagrange, eigenvalues, eigenvectors, np.linalg.inv(eigenvectors)
    )
