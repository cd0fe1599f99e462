r"""Nonholonomic systems in canonical coordinates, eq. (eq:HamEq).

Notation: state $(q, p) \in \mathbb{R}^n \times \mathbb{R}^n$,
$H = \tfrac12 p^T K(q) p + V(q)$ with $K = M^{-1} = \partial^2 H/\partial p^2$,
$v = \partial H/\partial p = Kp$, constraints $A(q) v = 0$ with $A$ of shape $(k, n)$,
$m = n - k$.
"""

from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._lagrangian import Lagrangian, LegendreAtPosition, LegendreHamiltonian
from ._linalg import is_quadratic_form, solve_spd
from ._householder import (
    HouseholderFrame,
    householder_frame_operator,
    householder_pivots,
    householder_signs,
    householder_stable_frame,
)
from ._results import RESULTS, first_failure
from ._reduced import Derivative, ReducedSystem
from ._user_function import check_function, traced_once
from ._system import (
    AbstractSystem,
    check_dissipation_and_force,
    dissipation_at_start,
    in_state_dtype,
    require_floating_vector,
    require_scalar,
    require_state_dtype,
    SkewGradientSystem,
)


# Multiples of eps in the initial-state checks: loose enough for states built in
# floating point, tight enough that what passes is preserved to the same level.
_CHECK_TOLERANCE = 1000


def _tolerance(dtype, scale):
    return _CHECK_TOLERANCE * jnp.finfo(dtype).eps * (1 + scale)


class HamiltonianAtPosition(eqx.Module):
    r"""$p \mapsto H(q, p)$ at one position, for a Hamiltonian given as such: its
    derivatives by autodiff of $H$ (`NonholonomicSystem.at_position`)."""

    hamiltonian: Callable
    q: Float[Array, " n"]
    args: Any

    def inverse_metric(self) -> Float[Array, "n n"]:
        return jax.jacfwd(self.velocity)(jnp.zeros_like(self.q))

    def velocity(self, p: Float[Array, " n"]) -> Float[Array, " n"]:
        return jax.grad(self.hamiltonian, argnums=1)(self.q, p, self.args)

    def momentum(self, v: Float[Array, " n"], inverse_metric: Float[Array, "n n"] | None = None) -> Float[Array, " n"]:
        """$M v$, by a solve with $K$ (`inverse_metric`, where the caller has formed it)."""
        return solve_spd(self.inverse_metric() if inverse_metric is None else inverse_metric, v)

    def position_gradient(self, p: Float[Array, " n"]) -> Float[Array, " n"]:
        return jax.grad(self.hamiltonian, argnums=0)(self.q, p, self.args)


class _InVelocities(eqx.Module):
    r"""A dissipation `function(q, qdot, args)` or force `function(t, q, qdot, args)`
    given in velocities (`NonholonomicSystem.from_lagrangian`), called in canonical
    coordinates with $\dot q = \partial H/\partial p$."""

    owns_tracing: ClassVar[bool] = True
    function: Callable = eqx.field(converter=traced_once)
    hamiltonian: LegendreHamiltonian

    def __call__(self, *arguments):
        *time, q, p, args = arguments
        return self.function(*time, q, jax.grad(self.hamiltonian, argnums=1)(q, p, args), args)


class NonholonomicSystem(AbstractSystem):
    r"""A mechanical system with linear velocity constraints, eq. (eq:HamEq), with an
    optional dissipation $D$ and force $F$:

    $$\dot q = v = \frac{\partial H}{\partial p}, \qquad
      \dot p = -\frac{\partial H}{\partial q} - D(q, p)\,v + F(t, q, p) + A(q)^T\lambda,
      \qquad A(q)\,v = 0.$$

    Its energy balance is $\dot H = v^TF - v^TDv$ (`power`): the constraint force does
    no work, $v^TA^T\lambda = 0$. Without $D$ and $F$ the system is conservative and
    $H$ is a first integral.

    **Arguments:**

    - `hamiltonian`: `hamiltonian(q, p, args) -> scalar`, of mechanical type
        $H = \tfrac12 p^T M(q)^{-1} p + V(q)$ with $M$ symmetric positive definite.
        The metric comes from autodiff: $M^{-1} = \partial^2 H/\partial p^2$.
    - `constraints`: `constraints(q, args) -> (k, n)` matrix $A(q)$ of full rank $k < n$.
    - `dissipation`: `None`, or `dissipation(q, p, args) -> (n, n)`, $D$, symmetric
        positive semidefinite (Rayleigh damping $\tfrac12v^TDv$, possibly state
        dependent).
    - `force`: `None`, or `force(t, q, p, args) -> (n,)`, $F$, a generalized force
        (motor torques $B(q)u(t)$, a feedback law).

    The state is the tuple `(q, p)`. As a diffrax term its vector field is the index-1
    ODE with the multiplier eliminated (`multiplier`), so any diffrax solver integrates
    it; nhjax's methods use the functions themselves.

    `nhjax.integrate` checks the initial state: finite; $H$, its gradient and $A$
    finite there; $H$ of mechanical type there
    (quadratic in $p$, no term linear in $p$, $M^{-1}$ positive definite, probed along
    $p_0$ and two fixed directions); $A(q_0)$ of full rank (`rank_result`); and
    $|A(q_0) v_0| \le 1000\epsilon(1 + |A||v_0|)$ (max norms). `project_momentum` puts a
    momentum on the constraint.

    A system given by its Lagrangian: `NonholonomicSystem.from_lagrangian`.
    """

    # Each called through `equinox.filter_jit`, so that a step's many evaluations and
    # derivatives of them trace the user's code once (`nhjax._user_function`).
    hamiltonian: Callable[[Float[Array, " n"], Float[Array, " n"], Any], Float[Array, ""]] = eqx.field(
        converter=traced_once
    )
    constraints: Callable[[Float[Array, " n"], Any], Float[Array, "k n"]] = eqx.field(converter=traced_once)
    dissipation: Callable[[Float[Array, " n"], Float[Array, " n"], Any], Float[Array, "n n"]] | None = eqx.field(
        default=None, converter=traced_once
    )
    force: Callable[[Any, Float[Array, " n"], Float[Array, " n"], Any], Float[Array, " n"]] | None = eqx.field(
        default=None, converter=traced_once
    )

    def __check_init__(self):
        check_function("NonholonomicSystem", "hamiltonian", self.hamiltonian, "hamiltonian(q, p, args) -> scalar")
        check_function("NonholonomicSystem", "constraints", self.constraints, "constraints(q, args) -> (k, n)")
        check_function(
            "NonholonomicSystem", "dissipation", self.dissipation, "dissipation(q, p, args) -> (n, n)", optional=True
        )
        check_function("NonholonomicSystem", "force", self.force, "force(t, q, p, args) -> (n,)", optional=True)

    @classmethod
    def from_lagrangian(
        cls,
        lagrangian: Lagrangian,
        constraints: Callable[[Float[Array, " n"], Any], Float[Array, "k n"]],
        *,
        dissipation: Callable[[Float[Array, " n"], Float[Array, " n"], Any], Float[Array, "n n"]] | None = None,
        force: Callable[[Any, Float[Array, " n"], Float[Array, " n"], Any], Float[Array, " n"]] | None = None,
    ) -> "NonholonomicSystem":
        r"""The system of `lagrangian(q, qdot, args) -> scalar`, of mechanical type
        $L = \tfrac12\dot q^TM(q)\dot q - V(q)$ with $M$ symmetric positive definite,
        and the constraints $A(q)\dot q = 0$: its Hamiltonian is the Legendre transform
        $H = \tfrac12p^TM(q)^{-1}p + V(q)$ with $M = \partial^2L/\partial\dot q^2(q, 0)$
        and $V = -L(q, 0)$, by autodiff (`nhjax._lagrangian.LegendreHamiltonian`), and
        the state is $(q, p)$ with $p = M(q)\dot q$ (`momentum_from_velocity`).

        A Lagrangian that is not of mechanical type (not quadratic in $\dot q$, a term
        linear in $\dot q$, $M$ not positive definite) would give a Hamiltonian of
        another system: `nhjax.integrate` checks the type at the initial state and at
        the end of every step of an nhjax method (`step_result`), each time along the
        velocity there and two fixed directions, and reports
        `RESULTS.lagrangian_not_mechanical`. What is not checked: directions of
        $\dot q$ that no velocity of the run takes (a term such as $(\dot q_0\dot
        q_1)^2$ along a run with $\dot q_1 = 0$ throughout is invisible, and harmless
        to it), and the interior of a step; diffrax's solvers (`nhjax.Projection`
        included) are checked at the start only.

        Every method integrates it as it integrates a system given by $H$; the
        Hamiltonian costs a solve with $M(q)$ per evaluation, which a system written
        with $H$ directly may avoid.

        `dissipation(q, qdot, args) -> (n, n)` and `force(t, q, qdot, args) -> (n,)`
        mean what they mean for a system given by $H$, in velocities: $D$ of the
        Rayleigh function $\tfrac12\dot q^TD\dot q$, and the generalized force; the
        system evaluates them at $\dot q = \partial H/\partial p$."""
        check_function("NonholonomicSystem.from_lagrangian", "lagrangian", lagrangian, "lagrangian(q, qdot, args) -> scalar")
        hamiltonian = LegendreHamiltonian(lagrangian)
        return cls(
            hamiltonian,
            constraints,
            None if dissipation is None else _InVelocities(dissipation, hamiltonian),
            None if force is None else _InVelocities(force, hamiltonian),
        )

    def momentum_from_velocity(self, q, qdot, args) -> Float[Array, " n"]:
        r"""$p = M(q)\dot q$ ($= \partial L/\partial\dot q$), the momentum of the
        velocity `qdot`: a state from positions and velocities. For a system given by
        its Lagrangian, $M = \partial^2L/\partial\dot q^2$ itself; otherwise the
        inverse of $\partial^2H/\partial p^2$. Called with concrete arrays, it raises
        a `ValueError` where $M$ is not symmetric positive definite (singular, say):
        no momentum describes the velocity then."""
        if isinstance(self.hamiltonian, LegendreHamiltonian):
            metric, name = self.hamiltonian.mass_matrix(q, args), "The mass matrix d^2L/dqdot^2"
        else:
            metric, name = self.metric(q, args), "The metric M(q), the inverse of d^2H/dp^2,"
        if not isinstance(metric, jax.core.Tracer):
            positive = bool(jnp.all(jnp.isfinite(jnp.linalg.cholesky(metric))))
            symmetric = bool(jnp.max(jnp.abs(metric - metric.T)) <= _tolerance(metric.dtype, jnp.max(jnp.abs(metric))))
            if not (positive and symmetric):
                raise ValueError(
                    f"{name} is not symmetric positive definite at q = {q} (singular, "
                    f"indefinite or not finite): {metric}. The system is not of mechanical type there."
                )
        return metric @ qdot

    # Mechanics.

    def velocity(self, q, p, args) -> Float[Array, " n"]:
        """$v = \\partial H/\\partial p$."""
        return jax.grad(self.hamiltonian, argnums=1)(q, p, args)

    def at_position(self, q, args) -> "HamiltonianAtPosition | LegendreAtPosition":
        r"""$p \mapsto H(q, p)$ at one position: `.velocity(p)` $= \partial_pH(q, p)$,
        `.position_gradient(p)` $= \partial_qH(q, p)$, `.inverse_metric()` $= K(q)$ and
        `.momentum(v)` $= M(q)v$, with what depends on $q$ alone
        formed once where the system's form allows (from its Lagrangian, $M(q)^{-1}$:
        `nhjax._lagrangian.LegendreAtPosition`)."""
        if isinstance(self.hamiltonian, LegendreHamiltonian):
            return self.hamiltonian.at_position(q, args)
        return HamiltonianAtPosition(self.hamiltonian, q, args)

    def inverse_metric(self, q, args) -> Float[Array, "n n"]:
        """$K(q) = M(q)^{-1} = \\partial^2 H/\\partial p^2$."""
        zero = jnp.zeros_like(q)
        return jax.jacfwd(self.velocity, argnums=1)(q, zero, args)

    def metric(self, q, args) -> Float[Array, "n n"]:
        """$M(q)$, the inverse of `inverse_metric`."""
        inverse = self.inverse_metric(q, args)
        return solve_spd(inverse, jnp.eye(q.shape[0], dtype=inverse.dtype))

    def constraint_residual(self, y, args) -> Float[Array, " k"]:
        """$A(q)\\,\\partial H/\\partial p$, zero on the constraint."""
        q, p = y
        return self.constraints(q, args) @ self.velocity(q, p, args)

    def multiplier(self, y, args, t=0.0) -> Float[Array, " k"]:
        r"""$\lambda$ from $\tfrac{d}{dt}[A(q)v] = 0$:
        $A K A^T\lambda = A K (\partial_q H + Dv - F) - \partial_q(Av)[v]$
        (differentiating the constraint along the flow; $D$ and $F$ at time `t`, where
        the system has them)."""
        return self._index_one(t, y, args)[2]

    def _index_one(self, t, y, args) -> tuple[Array, Array, Array, Array]:
        r"""$v$, the force $-\partial_qH - Dv + F$, $\lambda$ (`multiplier`) and $A$. A
        system given by its Lagrangian has its terms from one formation of $M$
        (`LegendreHamiltonian.index_one_terms`)."""
        q, p = y
        a = self.constraints(q, args)
        if isinstance(self.hamiltonian, LegendreHamiltonian):
            v, ka_t, position_gradient, velocity_turn = self.hamiltonian.index_one_terms(q, p, a, args)
            _, constraint_turn = jax.jvp(lambda x: self.constraints(x, args), (q,), (v,))
            drift = constraint_turn @ v + velocity_turn
        else:
            position_gradient, v = jax.grad(self.hamiltonian, argnums=(0, 1))(q, p, args)
            _, drift = jax.jvp(lambda x: self.constraints(x, args) @ self.velocity(x, p, args), (q,), (v,))
            # K by n tangents, not the velocities at the k momenta a_i (H quadratic in
            # p): their vmap inside an ensemble's vmap rounded apart from a single run's,
            # and a trajectory's iteration counts with it (tests/test_ensemble.py).
            ka_t = self.inverse_metric(q, args) @ a.T
        force = -position_gradient
        applied = self.applied_force(t, q, p, args, velocity=v)
        if applied is not None:
            force = force + applied
        return v, force, solve_spd(a @ ka_t, -ka_t.T @ force - drift), a

    def applied_force(self, t, q, p, args, velocity=None) -> Float[Array, " n"] | None:
        r"""$-D(q, p)\,v + F(t, q, p)$, the force of the dissipation and the force on the
        system, with $v = \partial_pH(q, p)$ or a method's discrete `velocity`; `None`
        for a conservative system."""
        if not self.is_forced():
            return None
        v = self.velocity(q, p, args) if velocity is None else velocity
        applied = jnp.zeros_like(v)
        if self.dissipation is not None:
            applied = applied - self.dissipation(q, p, args) @ v
        if self.force is not None:
            applied = applied + self.force(t, q, p, args)
        return applied

    def field(self, t, y, args):
        return self.field_and_multiplier(t, y, args)[0]

    def field_and_multiplier(self, t, y, args) -> tuple[tuple[Array, Array], Array]:
        """`field` and `multiplier` from one evaluation (a method's predictor needs both)."""
        v, force, multiplier, a = self._index_one(t, y, args)
        return (v, force + a.T @ multiplier), multiplier

    def power(self, t, y, args):
        q, p = y
        return self.power_along(t, q, p, self.velocity(q, p, args), args)

    def power_along(self, t, q, p, velocity, args) -> tuple[Float[Array, ""], Float[Array, ""]]:
        r"""(supplied, dissipated) $= (v^TF(t, q, p),\ v^TD(q, p)v)$ for a velocity $v$:
        `power` at $v = \partial_pH$, and a method's discrete power at its discrete
        velocity (times the step, its `exchange`)."""
        zero = jnp.zeros((), velocity.dtype)
        supplied = zero if self.force is None else velocity @ self.force(t, q, p, args)
        dissipated = zero if self.dissipation is None else velocity @ self.dissipation(q, p, args) @ velocity
        return supplied, dissipated

    def energy(self, y, args):
        return self.hamiltonian(*y, args)

    def observables(self, y, args):
        r"""The energy and the constraint residual $A(q)\,\partial H/\partial p$, from
        one evaluation of $H$ and its gradient in $p$ (a save's program traces $H$
        once, not once for each)."""
        q, p = y
        energy, velocity = jax.value_and_grad(self.hamiltonian, argnums=1)(q, p, args)
        return {"energy": energy, "constraint": self.constraints(q, args) @ velocity}

    def project_momentum(self, q, p, args=None) -> Float[Array, " n"]:
        r"""The momentum closest to `p` in the kinetic-energy norm that satisfies the
        constraint: $p - A^T(AKA^T)^{-1}AKp$, so that $A K p' = 0$."""
        return p + self.constraints(q, args).T @ self.projection_impulse(q, p, args)

    def projection_impulse(self, q, p, args=None) -> Float[Array, " k"]:
        r"""The $c = -(AKA^T)^{-1}AKp$ of `project_momentum`, whose constraint impulse
        $A^Tc$ takes `p` onto $\mathcal{D}^*(q)$."""
        a = self.constraints(q, args)
        ka_t = self.inverse_metric(q, args) @ a.T
        return -solve_spd(a @ ka_t, ka_t.T @ p)

    # The reduced system on D*.

    def frame_signs(self, q, args) -> Float[Array, " k"]:
        """The Householder sign choices at `q` (see `nhjax._householder`)."""
        return householder_signs(self.constraints(q, args).T)

    def stable_frame(self, q, args) -> tuple[HouseholderFrame, Float[Array, " k"]]:
        """`frame_operator(q, args, frame_signs(q, args))` and `frame_signs(q, args)`,
        from one factorisation: what a step that takes its signs at its start needs
        there."""
        return householder_stable_frame(self.constraints(q, args).T)

    def frame(self, q, args, signs) -> Float[Array, "n m"]:
        """$X(q; s)$: orthonormal columns spanning $\\mathcal{D}_q = \\ker A(q)$."""
        return self.frame_operator(q, args, signs).matrix()

    def frame_operator(self, q, args, signs) -> HouseholderFrame:
        """$X(q; s)$ as its reflectors, for products with $X$ and $X^T$ without
        forming it (`nhjax._householder.HouseholderFrame`)."""
        return householder_frame_operator(self.constraints(q, args).T, signs)

    def step_result(self, y0, y1, args) -> RESULTS:
        """`rank_result` at the step's end with the stable signs at its start: $A$ lost
        rank at $q'$ or between $q$ and $q'$; for a system given by its Lagrangian,
        before it, the Lagrangian's type at the step's end, along the velocity there
        (`from_lagrangian`)."""
        q1, p1 = y1
        return first_failure(
            self._lagrangian_result(q1, self.velocity(q1, p1, args), args),
            self.rank_result(q1, args, self.frame_signs(y0[0], args)),
        )

    def rank_result(self, q, args, signs=None) -> RESULTS:
        r"""`RESULTS.constraints_rank_deficient` if $A(q)$ has lost full row rank, else
        success. From one Householder factorisation of $A(q)^T$ with the sign choices
        `signs` (`None`: the stable ones at $q$), two tests, both relative, so that
        they do not hinge on rounding:

        - some $|x_j| = |R_{jj}|$, the distance of row $j$ of $A$ from the span of the
          rows before it, is at most $1000\epsilon(1 + \max|A|)$;
        - some pivot $(|x_j|^2 + s_jx_{j,1}|x_j|)^{1/2}$ is at most $|x_j|/10$: with
          the signs of a step's frame, chosen stably at the step's start
          ($s_jx_{j,1} > 0$ there), $x_j$ has turned to within 8 degrees of $-s_je_1$,
          where the frame $X(\cdot; s)$ is singular. It passed through zero ($A$ lost
          rank between the step's ends, where no $|x_j|$ need be small) or turned by
          more than a right angle in one step: either way the step's frame is not
          smooth across the step.
        """
        a = self.constraints(q, args)
        pivots, norms = householder_pivots(a.T, signs)
        full_rank = jnp.all(norms > _tolerance(a.dtype, jnp.max(jnp.abs(a))))
        smooth = jnp.all(pivots > 0.1 * norms)
        return RESULTS.where(full_rank & smooth, RESULTS.successful, RESULTS.constraints_rank_deficient)

    def to_reduced(self, y, args, signs) -> Float[Array, " n+m"]:
        r"""$\zeta = (q, \rho)$ with $\rho = X^T p$, eq. (ptildetop)."""
        return ReducedSystem(self, signs).to_reduced(y, args)

    def from_reduced(self, zeta, args, signs) -> tuple[Array, Array]:
        """$(q, p)$ from $\\zeta = (q, \\rho)$, eq. (ptoptilde)."""
        return ReducedSystem(self, signs).from_reduced(zeta, args)

    def reduced(
        self, signs, derivative: Derivative = "autodiff", difference_step=None
    ) -> SkewGradientSystem:
        """The reduced system (dynamical) on $\\zeta = (q, \\rho)$ for the frame with
        sign choices `signs`, as a `SkewGradientSystem` a user can inspect or integrate:
        its Hamiltonian is $\\mathcal{H}(q, \\rho) = H(q, p(q, \\rho))$ and its structure
        is (PiMat) with the block (skewMat). See `ReducedSystem`."""
        reduced = ReducedSystem(self, signs, derivative, difference_step)
        return SkewGradientSystem(
            reduced.hamiltonian,
            reduced.structure,
            None if self.dissipation is None else reduced.dissipation,
            None if self.force is None else reduced.force,
        )

    # Validation.

    def check_shapes(self, y0, args):
        if not (isinstance(y0, tuple) and len(y0) == 2):
            raise ValueError(
                "The state of a NonholonomicSystem is the tuple (q, p), got "
                f"{type(y0).__name__}."
            )
        q, p = y0
        require_floating_vector("q", q)
        require_floating_vector("p", p)
        if jnp.shape(q) != jnp.shape(p):
            raise ValueError(f"q and p must have the same shape, got {jnp.shape(q)} and {jnp.shape(p)}.")
        if jnp.result_type(q) != jnp.result_type(p):
            # Otherwise a method's loop fails deep inside, its carry's dtype changing.
            raise ValueError(
                f"q and p must have the same dtype, got {jnp.result_type(q)} and {jnp.result_type(p)}: "
                "convert both to one (float64 keeps the energy to roundoff), e.g. with .astype."
            )
        (n,) = jnp.shape(q)
        dtype = jnp.result_type(q)
        converted = in_state_dtype(args, dtype)
        if isinstance(self.hamiltonian, LegendreHamiltonian):
            # Before the Hamiltonian's shape, which a Lagrangian of the wrong shape fails
            # deep inside the Legendre transform.
            lagrangian = jax.eval_shape(self.hamiltonian.lagrangian, q, p, converted)
            require_scalar("lagrangian(q, qdot, args)", lagrangian)
            require_state_dtype("lagrangian(q, qdot, args)", lagrangian, dtype)
        energy = jax.eval_shape(self.hamiltonian, q, p, converted)
        require_scalar("hamiltonian(q, p, args)", energy)
        require_state_dtype("hamiltonian(q, p, args)", energy, dtype)
        a = jax.eval_shape(self.constraints, q, converted)
        require_state_dtype("constraints(q, args)", a, dtype)
        if len(a.shape) != 2 or a.shape[1] != n or not 1 <= a.shape[0] < n:
            raise ValueError(
                f"constraints(q, args) must return a (k, {n}) matrix with 1 <= k < {n} for "
                f"q of shape ({n},), got shape {a.shape}."
            )
        in_velocities = isinstance(self.dissipation or self.force, _InVelocities)
        check_dissipation_and_force(self, (q, p), args, n, "q, qdot" if in_velocities else "q, p")

    def initial_state_result(self, y0, args):
        q, p = y0
        finite = jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(p))
        a = self.constraints(q, args)
        energy, (grad_q, v) = jax.value_and_grad(self.hamiltonian, argnums=(0, 1))(q, p, args)
        violation = jnp.max(jnp.abs(a @ v))
        satisfied = violation <= _tolerance(q.dtype, jnp.max(jnp.abs(a)) * jnp.max(jnp.abs(v)))
        dissipation_finite, dissipation = dissipation_at_start(self.dissipation, (q, p), args)
        evaluations_finite = (
            jnp.isfinite(energy)
            & jnp.all(jnp.isfinite(grad_q))
            & jnp.all(jnp.isfinite(v))
            & jnp.all(jnp.isfinite(a))
            & dissipation_finite
        )
        return first_failure(
            RESULTS.where(finite, RESULTS.successful, RESULTS.nonfinite_initial_state),
            # Before the Hamiltonian's checks: a Lagrangian of the wrong type is what the
            # user wrote, and its transform may fail them only as a consequence.
            self._lagrangian_result(q, v, args),
            RESULTS.where(evaluations_finite, RESULTS.successful, RESULTS.nonfinite_initial_evaluation),
            RESULTS.where(self._is_mechanical(q, p, args), RESULTS.successful, RESULTS.hamiltonian_not_mechanical),
            self.rank_result(q, args),
            RESULTS.where(satisfied, RESULTS.successful, RESULTS.constraint_violated_initially),
            dissipation,
        )

    def _lagrangian_result(self, q, v, args) -> RESULTS:
        if not isinstance(self.hamiltonian, LegendreHamiltonian):
            return RESULTS.successful
        mechanical = self.hamiltonian.is_mechanical(q, v, args, _tolerance)
        return RESULTS.where(mechanical, RESULTS.successful, RESULTS.lagrangian_not_mechanical)

    def _is_mechanical(self, q, p, args):
        """$H(q, u) = H(q, 0) + \\tfrac12 u^T K u$ along probes, $\\partial_p H(q, 0) = 0$
        and $K$ positive definite. For a system given by its Lagrangian, what
        `_lagrangian_result` checks of $L$ implies it (the transform of a mechanical
        $L$ with $M$ positive definite is $\\tfrac12p^TM^{-1}p + V$): not traced twice."""
        if isinstance(self.hamiltonian, LegendreHamiltonian):
            return jnp.asarray(True)
        return is_quadratic_form(
            lambda u: self.hamiltonian(q, u, args), self.inverse_metric(q, args), p, _tolerance
        )
