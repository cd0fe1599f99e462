r"""Energy-preserving collocation of order $2s$ for $\dot x = \Pi(x)\nabla H(x)$, on a
`SkewGradientSystem` and on the reduced form of a `NonholonomicSystem` (§3.3)."""

import functools
from typing import Any, ClassVar, NamedTuple

import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array
from numpy.polynomial import polynomial

from .._discrete_gradient import Branch, value_difference
from .._linalg import matrix_product, PRODUCT_LIMIT, rows_per_block, SEQUENTIAL_BYTES
from .._nonholonomic import NonholonomicSystem
from .._reduced import metric_of, ReducedSystem
from .._system import AbstractSystem, SkewGradientSystem
from ._collocation_tableau import collocation_tableau, CollocationTableau
from .base import (
    AbstractMethod,
    agrees,
    displacements_for_step,
    floor_of_rounding,
    HISTORY,
    increment_scale,
    resolution_of,
    step_key,
    with_displacement,
)
from .chord import chord_inverse, REMAINDER


# Up to six stages: the Gauss matrix's eigenvector basis, through which the chord
# matrix is inverted, has condition 600 at s = 6 and 2 200 at s = 7.
ORDERS = (2, 4, 6, 8, 10, 12)


class _Carry(NamedTuple):
    """What a step hands the next: its end in the coordinates it integrates ($x'$, or
    $\\zeta'$ on the reduced form, with the frame's signs), its increments $Z_j$ and its
    signed size, for the predictors (NaN until there are any), and the displacements
    $x_{k+1} - x_k$ of the last `HISTORY` steps of that size, newest first (NaN where
    there are fewer; see `EnergyPreservingCollocation`)."""

    end: Array
    signs: Array
    increments: Array
    step: Array
    displacements: Array


class _StepData(NamedTuple):
    """What the residual of one step needs (`EnergyPreservingCollocation.setup`)."""

    form: Any  # the SkewGradientSystem, or the step's ReducedSystem
    x: Array
    h: Any
    scale: Array
    args: Any
    energy: Array
    momentum: Array | None
    t: Any
    # The carry's displacements; after a restart or a change of step size, none.
    displacements: Array


class _Point(NamedTuple):
    r"""$\nabla H$ at a point, and what products with $\Pi$ there need (a
    `ReducedPoint` on the reduced form)."""

    gradient: Array
    reduced: Any


def _point(form, x, args) -> _Point:
    if isinstance(form, ReducedSystem):
        point = form.at(x, args)
        return _Point(point.gradient, point)
    return _Point(jax.grad(form.hamiltonian)(x, args), None)


def _stage_field(form, t, x, point: _Point, gradient, args):
    r"""$(\Pi(x) - R(x))\,$`gradient`$ + g(t, x)$ at a stage, and the power of the force
    and of the dissipation along `gradient` (`None` for a conservative system)."""
    if isinstance(form, ReducedSystem):
        field = point.reduced.structure_times(gradient)
        return form.with_applied_force(t, x, point.reduced, gradient, field, args)
    field = form.structure(x, args) @ gradient
    if not form.is_forced():
        return field, None
    return field + form.applied_force(t, x, args, gradient), form.power_along(t, x, gradient, args)


@functools.cache
def _history_weights(nodes: tuple) -> np.ndarray:
    r"""$w_{ij} = L_j'(c_i)$, $L_j$ the Lagrange polynomials of the step ends
    $0, -1, \dots, -(m - 1)$ ($m$ = `HISTORY`, in units of the step): the history
    predictor's $Z_i \approx Z_i^{\text{prev}} + \sum_jw_{ij}\delta_j$ (see
    `EnergyPreservingCollocation`)."""
    ends = -np.arange(HISTORY, dtype=float)
    weights = np.zeros((len(nodes), HISTORY))
    for j in range(HISTORY):
        others = np.delete(ends, j)
        basis = polynomial.polyfromroots(others) / np.prod(ends[j] - others)
        weights[:, j] = polynomial.polyval(np.asarray(nodes), polynomial.polyder(basis))
    return weights


class EnergyPreservingCollocation(AbstractMethod):
    r"""Energy-preserving collocation at $s$ Gauss nodes, order $2s$: symmetric, and
    exact in the energy (and, on the reduced form of a `NonholonomicSystem`, in the
    constraint) to roundoff at every step size.

    For $\dot x = \Pi(x)\nabla H(x)$, $\Pi$ skew (a `SkewGradientSystem`, or the reduced
    equations (dynamical) of a `NonholonomicSystem` in $\zeta = (q, \rho)$, with $\Pi$
    and $\nabla\mathcal{H}$ from $H$ and $A$ alone, as `nhjax.GonzalezR` evaluates them),
    the step is the polynomial $u$ of degree $s$ with $u(t_0) = x_0$ and

    $$\dot u(t_0 + c_ih) = \Pi(u(t_0 + c_ih))\,G_i,\qquad
      G_i = \int_0^1\frac{\ell_i(\tau)}{b_i}\nabla H(u(t_0 + \tau h))\,d\tau,
      \qquad x_1 = u(t_0 + h)$$

    (Cohen & Hairer, "Linear energy-preserving integrators for Poisson systems", BIT
    51 (2011) 91; for constant $\Pi$, Hairer, "Energy-preserving variant of collocation
    methods", JNAIAM 5 (2010) 73). As $\dot u$ is the polynomial of degree $s - 1$
    through the $K_i = \dot u(t_0 + c_ih)$,
    $H(x_1) - H(x_0) = h\int_0^1\nabla H(u)^T\dot u\,d\tau = h\sum_ib_iG_i^TK_i
    = h\sum_ib_iG_i^T\Pi_iG_i = 0$. The method is symmetric for the symmetric Gauss
    nodes, and of order $2s$.

    **The integral, and exact energy with any quadrature.** $G_i$ is computed by the
    $r$-point Gauss rule (`quadrature_nodes`, default $r = s$: the gradients at the
    stage values, no evaluation beyond them), whose error $O(h^{2r})$ would leave
    the energy wrong by $O(h^{2r+1})$ per step unless $\nabla H^T\dot u$ were a
    polynomial of degree below $2r$. nhjax removes that error as the Gonzalez
    discrete gradient does for the midpoint rule: with $\tilde G_i$ the quadrature and
    $\delta = x_1 - x_0$,

    $$G_i = \tilde G_i + \kappa\,\delta,\qquad
      \kappa = \frac{H(x_1) - H(x_0) - \sum_ib_i\tilde G_i^TZ_i}{|\delta|^2},
      \qquad Z_i = hK_i,$$

    so that $\sum_ib_iG_i^TZ_i = H(x_1) - H(x_0)$ holds identically, and with
    $Z_i = h\Pi_iG_i$ (skew) both sides vanish: the energy is kept to roundoff
    whatever $H$ is, by the same argument as (discGradEn). The correction is
    the quadrature's error over $|\delta|^2$, $O(h^{2r - 1})$, which changes the step
    by $O(h^{2r + 1})$: the order stays $2s$ for every $r \ge s$. It is symmetric (the
    reversed step reverses $\delta$, the numerator's sign and the Gauss nodes), and
    for $s = r = 1$ it is the Gonzalez discrete gradient with $\Pi$ at the midpoint.
    $H(x_1) - H(x_0)$ comes from the values, or for nearly equal points from gradients
    along the segment (`nhjax._discrete_gradient.value_difference`), as for GONZALEZ-R.

    **On the reduced form** each stage needs the frame and its derivative at the stage
    value (`nhjax._reduced.ReducedSystem.at`), with the signs of the step's start kept
    for every factorisation in the step, so that every stage's frame belongs to one
    smooth basis; $q$-increments lie in $\mathcal{D}$ at each stage, and the returned
    $p' = p(\zeta')$ satisfies $A(q')\partial_pH(q', p') = 0$ to roundoff.

    **The step's equations** are solved for the scaled increments $Z_j/S$
    ($S = 1 + |x_0|$) by the chord iteration with the simplified-Newton matrix
    $I - h\,(a \otimes F)$ of the Gauss method, $F$ the field's derivative at the
    predicted midpoint (on the reduced form with the frame held fixed,
    `ReducedSystem.field_jacobian`).

    **Predictors.** The last step's collocation polynomial extrapolated,
    $K_i \approx \sum_j\ell_j(1 + c_ih/h_{\text{prev}})K_j^{\text{prev}}$, is
    $O(h^s)$ from the root, relative to the increments. Once the last $m$ =
    `HISTORY` steps had this step's size, the step starts instead from the last
    step's increments moved on as the step ends say the trajectory moves:

    $$Z_i \approx Z_i^{\text{prev}} + \sum_{j=0}^{m-1}L_j'(c_i)\,\delta_j,$$

    $\delta_j = x_{k-j} - x_{k-j-1}$ the displacement of the $(j+1)$-th last step and
    $L_j$ the Lagrange polynomials of the nodes $0, -1, \dots, -(m-1)$: the sum is the
    derivative (times $h$) at $t_k + c_ih$ of the polynomial through the last $m$ step
    ends, less that of the same polynomial one step back at $t_{k-1} + c_ih$. The step
    ends lie on a smooth curve (the flow and the smooth global error), and so does the
    stage increments' departure from it, which the last step's increments carry
    forward. Its error is $O(h^m)$ (fitted 6.0 to 6.1 on the gearbox at orders 4 and
    6, 5.1 to 5.5 on the quartic at order 4; on the gearbox at order 4 and
    $h = 0.02$, $8 \cdot 10^{-9}$ of the increments against $4 \cdot 10^{-4}$ for the
    extrapolation): a chord iteration fewer per step at the step sizes at which order 4
    reaches $10^{-8}$ (`benchmarks/composition.py`). Where a step is long against the
    motion, a polynomial through $m$ step ends extrapolates wildly (the quartic at
    order 12 and $h = 0.7$: errors 7 times the increments, against 0.7 for the
    extrapolation), so it is taken only where the two predictions agree to
    `AGREEMENT` (1%) of the increments: there both are close, and the history is the
    closer. No motion where there is no last step (the first step, a restart, a
    change of the frame's signs, a step size more than four times the last), from
    which the iteration's first iterate is a linearly implicit step.

    **Arguments:**

    - `order`: 2, 4, 6, 8, 10 or 12 ($s$ = `order / 2` stages; `orders`). The
        stage fields are evaluated together (`jax.vmap`), so a step's program and its
        count of operations grow little with $s$, while the step a target error allows
        grows: towards tight errors the highest orders are the cheapest
        (`benchmarks/composition.py`).
    - `quadrature_nodes`: $r \ge s$ (default $s$); more nodes make the correction
        smaller, not the energy more exact.
    - `root_finder`, `root_find_max_steps`: as for `nhjax.DiscreteGradient`.
    - `reuse_chord_matrix`: start each step from the last step's chord matrix while
        it serves (`nhjax.AbstractMethod.reuses_chord_matrix`): its $sN \times sN$
        matrix, from the field's derivative and $s/2$ real $N \times N$ inverses,
        can cost as much as several iterations.

    **Dissipation and force.** For $\dot x = (\Pi - R)\nabla H + g(t, x)$ (on the
    reduced form $R_\zeta$ and $g_\zeta$, as for GONZALEZ-R) the stage equations are
    $K_i = (\Pi_i - R_i)G_i + g_i$ with $R$, $g$ at the stage value and time
    $t_0 + c_ih$, and the same identity gives the discrete power balance
    $$H(x_1) - H(x_0) = h\sum_ib_iG_i^Tg_i - h\sum_ib_iG_i^TR_iG_i$$
    to roundoff (the step's `exchange`), the collocation form of Celledoni &
    Høiseth's balance (arXiv:1706.08621); still symmetric, and collocation at the
    stage times keeps the order for a time-dependent force. Measured
    against GONZALEZ-R's compositions and Dopri8 in `benchmarks/composition.py`
    (`benchmarks/results/composition.json`).
    """

    # Both forms: the registry and the command line take it for canonical systems.
    term_structure: ClassVar = AbstractSystem
    orders: ClassVar[tuple[int, ...]] = ORDERS

    stages: int = 2
    quadrature_nodes: int | None = None
    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 20
    reuse_chord_matrix: bool = False

    def __init__(
        self,
        order: int = 4,
        quadrature_nodes: int | None = None,
        root_finder: optx.AbstractRootFinder | None = None,
        root_find_max_steps: int = 20,
        reuse_chord_matrix: bool = False,
    ):
        if isinstance(order, bool) or order not in ORDERS:
            raise ValueError(f"EnergyPreservingCollocation: order must be one of {ORDERS}, got {order!r}.")
        stages = order // 2
        if quadrature_nodes is not None and (
            isinstance(quadrature_nodes, bool) or not isinstance(quadrature_nodes, int) or quadrature_nodes < stages
        ):
            raise ValueError(
                f"EnergyPreservingCollocation: quadrature_nodes must be an integer of at least {stages} (the "
                f"stages of order {order}): a coarser quadrature of the gradient along the step lowers the "
                f"order; got {quadrature_nodes!r}."
            )
        self.stages = order // 2
        self.quadrature_nodes = quadrature_nodes
        self.root_finder = root_finder
        self.root_find_max_steps = root_find_max_steps
        self.reuse_chord_matrix = bool(reuse_chord_matrix)

    def tableau(self) -> CollocationTableau:
        return collocation_tableau(self.stages, self.stages if self.quadrature_nodes is None else self.quadrature_nodes)

    def order(self, terms) -> int:
        del terms
        return 2 * self.stages

    def is_symmetric(self) -> bool:
        return True

    def keeps_energy(self) -> bool:
        return True

    def keeps_constraint(self) -> bool:
        return True

    def summary(self) -> str:
        return (
            f"energy-preserving collocation at {self.stages} Gauss nodes (Cohen & Hairer), on the reduced "
            "system of a canonical one or on a skew-gradient system"
        )

    def _form(self, system, y0, args, signs):
        if isinstance(system, NonholonomicSystem):
            return ReducedSystem(system, signs, metric=metric_of(system, y0, args))
        if isinstance(system, SkewGradientSystem):
            return system
        raise ValueError(
            "EnergyPreservingCollocation integrates a NonholonomicSystem (through its reduced form) or a "
            f"SkewGradientSystem, got {type(system).__name__}."
        )

    def _signs_and_frame(self, system, y0, args):
        """The frame's signs at the start of a step (none for a `SkewGradientSystem`),
        and the frame with them there, from one factorisation (`None` without one)."""
        if isinstance(system, NonholonomicSystem):
            frame, signs = system.stable_frame(y0[0], args)
            return lax.stop_gradient(signs), frame
        return jnp.zeros((0,), dtype=jax.tree.leaves(y0)[0].dtype), None

    def initial_carry(self, system, y0, args):
        signs, frame = self._signs_and_frame(system, y0, args)
        form = self._form(system, y0, args, signs)
        start = form.to_reduced(y0, args, frame) if isinstance(form, ReducedSystem) else y0
        unknown = jnp.full((self.stages, start.shape[0]), jnp.nan, dtype=start.dtype)
        no_history = jnp.full((HISTORY, start.shape[0]), jnp.nan, dtype=start.dtype)
        return _Carry(start, signs, unknown, jnp.full((), jnp.nan, dtype=start.dtype), no_history)

    def replayed_carry(self, carry: _Carry) -> _Carry:
        """The end and the signs: the increments, step size and displacements feed only
        the predictor (`setup`), which a replayed step does not use."""
        return carry._replace(increments=None, step=None, displacements=None)

    def setup(self, system, t, h, y0, args, carry):
        signs, frame = self._signs_and_frame(system, y0, args)
        form = self._form(system, y0, args, signs)
        if isinstance(form, ReducedSystem):
            # As GONZALEZ-R: a step starts from the last step's zeta' itself where the
            # state is the one it returned and the signs are the same (p -> rho -> p
            # rounds with a bias); the q of x is q either way, where the frame is.
            q = y0[0]
            continues = jnp.all(signs == carry.signs) & jnp.all(carry.end[: q.shape[0]] == q)
            x = jnp.where(continues, carry.end, form.to_reduced(y0, args, frame))
            energy, momentum = form.start_of_step(x, args, frame)
        else:
            continues = jnp.all(carry.end == y0)
            x, momentum = y0, None
            energy = form.hamiltonian(x, args)
        tableau = self.tableau()
        ratio = h / carry.step
        extrapolates = continues & jnp.all(jnp.isfinite(carry.increments)) & (jnp.abs(ratio) <= 4)
        # l_j(1 + c_i h / h_prev), from the coefficients of l_j.
        times = 1 + jnp.asarray(tableau.c, dtype=x.dtype) * ratio
        powers = times[:, None] ** jnp.arange(self.stages, dtype=x.dtype)
        extrapolation = powers @ jnp.asarray(tableau.lagrange, dtype=x.dtype).T
        extrapolated = ratio * extrapolation @ carry.increments
        # Without a last polynomial, no motion: the chord iteration's first iterate from
        # it is a linearly implicit Runge--Kutta step, which costs about what an
        # explicit Euler guess would (as for GONZALEZ-R), its field evaluations the
        # iteration's own residual, not a copy of the field in the step's program.
        displacements = displacements_for_step(continues, h, carry.step, carry.displacements)
        from_history = carry.increments + jnp.asarray(_history_weights(tuple(tableau.c)), dtype=x.dtype) @ displacements
        uses_history = extrapolates & agrees(from_history, extrapolated)
        increments = jnp.where(uses_history, from_history, jnp.where(extrapolates, extrapolated, 0.0))
        scale = increment_scale(x)
        guess = (lax.stop_gradient(increments) / scale).reshape(-1)
        return guess, _StepData(form, x, h, scale, args, energy, momentum, t, displacements)

    def residual(self, u, data, branch: Branch = "cond"):
        return self._equations(u, data, branch)[0]

    def residual_and_exchange(self, u, data):
        return self._equations(u, data)

    def exchange(self, u, data):
        r"""$h\sum_ib_iG_i^Tg_i$ and $h\sum_ib_iG_i^TR_iG_i$ (see the class
        docstring)."""
        return self._equations(u, data)[1]

    def _equations(self, u, data, branch: Branch = "cond"):
        """The residual, and the step's exchange (`None` for a conservative system)."""
        tableau = self.tableau()
        form, x, h, scale, args = data.form, data.x, data.h, data.scale, data.args
        increments = u.reshape(self.stages, -1) * scale
        stages = x + jnp.asarray(tableau.a, dtype=x.dtype) @ increments
        x1 = x + jnp.asarray(tableau.b, dtype=x.dtype) @ increments
        nodes = stages if tableau.shares_nodes else x + jnp.asarray(tableau.quadrature_points, dtype=x.dtype) @ increments
        gradients = jax.vmap(lambda node: _point(form, node, args).gradient)(nodes)
        averaged = jnp.asarray(tableau.quadrature_weights, dtype=x.dtype) @ gradients
        delta = x1 - x
        squared_length = delta @ delta
        zero = squared_length == 0
        if isinstance(form, ReducedSystem):
            energy1, segment = form.energy_segment(x, data.momentum, x1, args)
        else:
            energy1, segment = form.hamiltonian(x1, args), None
        difference = value_difference(
            form.hamiltonian, x, x1, args, branch=branch, f_x=data.energy, f_x1=energy1, segment=segment
        )
        quadrature = jnp.asarray(tableau.b, dtype=x.dtype) @ jnp.sum(averaged * increments, axis=1)
        coefficient = (difference - quadrature) / jnp.where(zero, 1.0, squared_length)
        corrected = averaged + jnp.where(zero, 0.0, coefficient) * delta
        times = data.t + jnp.asarray(tableau.c, dtype=x.dtype) * h
        # `_point` at the stages is traced again here (its products with Pi are
        # closures, which a vmap cannot return); XLA merges the copies, so the frames
        # are factorised once per stage.
        fields, powers = jax.vmap(
            lambda time, stage, g: _stage_field(form, time, stage, _point(form, stage, args), g, args)
        )(times, stages, corrected)
        residual = ((increments - h * fields) / scale).reshape(-1)
        if powers is None:
            return residual, None
        weights = h * jnp.asarray(tableau.b, dtype=x.dtype)
        return residual, (weights @ powers[0], weights @ powers[1])

    def root_find_residual(self, u, data):
        return self.residual(u, data, branch="rarely")

    def _scaled_field_jacobian(self, u, data):
        """$S^{-1}FS$, the field's derivative at the predicted midpoint in the scaled
        unknowns."""
        tableau = self.tableau()
        form, x, h, scale, args = data.form, data.x, data.h, data.scale, data.args
        increments = u.reshape(self.stages, -1) * scale
        middle = x + 0.5 * jnp.asarray(tableau.b, dtype=x.dtype) @ increments
        if isinstance(form, ReducedSystem):
            jacobian = form.field_jacobian(middle, data.t + 0.5 * h, args)
        else:
            jacobian = jax.jacfwd(lambda z: form.field(data.t + 0.5 * h, z, args))(middle)
        return jacobian * scale[None, :] / scale[:, None]

    def chord_jacobian(self, u, data):
        r"""$I - h\,(a \otimes F)$ in the scaled unknowns, $F$ the derivative of the field
        at the predicted midpoint $x_0 + \tfrac12\sum_jb_jZ_j$ (see the class
        docstring)."""
        return self._chord_jacobian_of(self._scaled_field_jacobian(u, data), data.h)

    def _chord_jacobian_of(self, scaled, h):
        r"""`chord_jacobian` from $F$ in the scaled unknowns, assembled from its $s^2$
        blocks $\delta_{ij}I - ha_{ij}F$: XLA:CPU forms that in about half the time of
        `jnp.kron` or of a broadcast $(s, N, s, N)$ array (the order-8 quartic)."""
        a = self.tableau().a
        identity = jnp.eye(scaled.shape[0], dtype=scaled.dtype)
        return jnp.block([
            [(identity if i == j else 0.0) - h * float(a[i, j]) * scaled for j in range(a.shape[0])]
            for i in range(a.shape[0])
        ])

    def chord_matrix(self, u, data, kept: bool = False):
        r"""The chord matrix, in the form of $F$ (scaled, `_scaled_field_jacobian`), from
        which `chord_jacobian` assembles it and `chord_floor` reads its rounding, and its
        inverse by the eigenvalues $\mu_k$ of $a$:
        $\sum_k (v_k w_k^T) \otimes (I - h\mu_kF)^{-1}$ ($v_k$, $w_k^T$ the columns
        of $V$ and rows of $V^{-1}$), one $N \times N$ block per real eigenvalue or
        conjugate pair (the conjugate's block is the conjugate) against $(sN)^3$ work by
        elimination; the sum is one real matrix product
        (`CollocationTableau.inverse_blocks`). A block is formed in real arithmetic,
        $(I - h\mu F)^{-1} = (I - h\bar\mu F)P^{-1}$ with
        $P = (I - h\mu F)(I - h\bar\mu F) = I - 2h\,\mathrm{Re}\,\mu\,F + h^2|\mu|^2F^2$,
        one real inverse (`chord_inverse`) and a product:
        its real part is $(I - h\,\mathrm{Re}\,\mu\,F)P^{-1}$, its imaginary part
        $h\,\mathrm{Im}\,\mu\,FP^{-1}$. $P$'s condition is that of the block
        squared, which a chord matrix can spare (it sets how fast the iteration
        contracts, not the root). On XLA:CPU a real elimination is a fraction of a
        complex one, and with the $sN \times sN$ matrix never assembled the steps of
        orders 8 to 12 are a tenth to a fifth cheaper than with complex blocks and the
        assembled matrix (`benchmarks/composition.py`). At order 2 ($s = 1$) the matrix
        is inverted as it is. Cut from differentiation, as the chord matrix is.

        Where the inverted blocks are small together (`SEQUENTIAL_BYTES`: in float64 up to
        $N = 5$ at orders 4 to 8), the inverse is returned in blocks of rows
        (`nhjax._linalg.row_blocks`), each formed from the rows of the $N \times N$
        parts, so that no array of the step is large: XLA:CPU then runs
        the step's operations in sequence, not on its thread pool, which for such tiny
        operations costs more than their arithmetic (the gearbox, $N = 5$, in
        `benchmarks/composition.py`)."""
        scaled = lax.stop_gradient(self._scaled_field_jacobian(u, data))
        h = lax.stop_gradient(data.h)
        if self.stages == 1:
            return scaled, chord_inverse(self._chord_jacobian_of(scaled, h), kept)
        eigenvalues, weights = self.tableau().inverse_blocks()
        real = jnp.asarray(eigenvalues.real, dtype=scaled.dtype)[:, None, None]
        imaginary = jnp.asarray(eigenvalues.imag, dtype=scaled.dtype)[:, None, None]
        modulus = jnp.asarray(np.abs(eigenvalues) ** 2, dtype=scaled.dtype)[:, None, None]
        identity = jnp.eye(scaled.shape[0], dtype=scaled.dtype)
        products = jax.vmap(functools.partial(chord_inverse, kept=kept))(
            identity - 2 * h * real * scaled + h * h * modulus * matrix_product(scaled, scaled)
        )
        turned = matrix_product(scaled[None], products)
        if products.nbytes <= SEQUENTIAL_BYTES:
            # The blocks formed from the parts' rows: no array of the step is large.
            parts = [products[k] - h * real[k] * turned[k] for k in range(len(eigenvalues))]
            parts += [h * imaginary[k] * turned[k] for k in range(len(eigenvalues))]
            return scaled, self._row_blocks_from_parts(parts, weights)
        parts = jnp.concatenate([products - h * real * turned, h * imaginary * turned])
        stages, size = self.stages, scaled.shape[0]
        inverse = (
            jnp.asarray(weights.reshape(stages * stages, -1), dtype=parts.dtype) @ parts.reshape(-1, size * size)
        ).reshape(stages, stages, size, size)
        return scaled, inverse.transpose(0, 2, 1, 3).reshape(u.shape[0], u.shape[0])

    def _row_blocks_from_parts(self, parts, weights) -> tuple[Array, ...]:
        r"""The inverse $\sum_k W_k \otimes P_k$ (`weights` $W$, `parts` $P_k$, each
        $N \times N$) in blocks of rows of at most `SEQUENTIAL_BYTES`, each formed from
        the parts' rows, within one stage's rows."""
        size = parts[0].shape[0]
        per_block = rows_per_block(self.stages * size, parts[0].dtype)
        blocks = []
        for i in range(self.stages):
            for start in range(0, size, per_block):
                rows = slice(start, min(start + per_block, size))
                blocks.append(jnp.concatenate(
                    [
                        sum(
                            (float(weights[i, j, k]) * part[rows] for k, part in enumerate(parts) if weights[i, j, k]),
                            jnp.zeros_like(parts[0][rows]),
                        )
                        for j in range(self.stages)
                    ],
                    axis=1,
                ))
        return tuple(blocks)

    def chord_floor(self, scaled, data):
        r"""`nhjax._solver.base.rounding_floor` of the chord matrix
        $I - h\,(a \otimes F)$, from $F$: row block $i$ of $|\tilde J|\,r$ is
        $\sum_j|ha_{ij}|\,|F|\,r_j$ with the diagonal of the block $(i, i)$ taken as
        $|1 - ha_{ii}F_{kk}|$."""
        resolution, scale = self.resolution(data)
        ha = lax.stop_gradient(data.h) * jnp.asarray(self.tableau().a, dtype=scaled.dtype)
        size = scaled.shape[0]
        rounding = resolution.reshape(self.stages, size)
        diagonal, on_diagonal = jnp.diagonal(scaled), jnp.diagonal(ha)[:, None]
        if size > PRODUCT_LIMIT:
            spread = jnp.abs(ha) @ (rounding @ jnp.abs(scaled).T)
        else:
            # Broadcasts, fused by XLA:CPU, where dots are library calls of their own.
            spread = jnp.sum(jnp.abs(scaled)[None] * rounding[:, None, :], axis=-1)
            spread = jnp.sum(jnp.abs(ha)[:, :, None] * spread[None], axis=1)
        own = spread + rounding * (jnp.abs(1 - on_diagonal * diagonal) - jnp.abs(on_diagonal * diagonal))
        return floor_of_rounding(own.reshape(-1), scale)

    def reuses_chord_matrix(self, system, y0, args) -> bool:
        """`reuse_chord_matrix` (see `nhjax.AbstractMethod.reuses_chord_matrix`)."""
        del system, y0, args
        return self.reuse_chord_matrix

    def chord_key(self, data):
        """The step size, and on the reduced form the frame's signs, for which the
        chord matrix holds."""
        return step_key(data.h, data.x.dtype, data.form.signs if isinstance(data.form, ReducedSystem) else None)

    def chord_remainder(self, data):
        """The chord matrix holds the field's derivative at one point (and, on the
        reduced form, the frame fixed): the iteration contracts only by $O(h)$ and goes
        on until the error it leaves is below the rounding (`REMAINDER`)."""
        del data
        return REMAINDER

    def resolution(self, data):
        resolution = resolution_of(data.x, data.scale)
        return jnp.tile(resolution, self.stages), jnp.tile(data.scale, self.stages)

    def complete(self, u, data):
        tableau = self.tableau()
        form, x, args = data.form, data.x, data.args
        increments = u.reshape(self.stages, -1) * data.scale
        x1 = x + jnp.asarray(tableau.b, dtype=x.dtype) @ increments
        y1 = form.from_reduced(x1, args) if isinstance(form, ReducedSystem) else x1
        signs = form.signs if isinstance(form, ReducedSystem) else jnp.zeros((0,), dtype=x.dtype)
        return y1, _Carry(
            end=x1,
            signs=signs,
            increments=lax.stop_gradient(increments),
            step=lax.stop_gradient(jnp.asarray(data.h, dtype=x.dtype)),
            displacements=with_displacement(data.displacements, x1 - x),
        )

