r"""The discrete-gradient method (E-int) for $\dot x = \Pi(x)\nabla H(x)$."""

import functools
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple

import optimistix as optx

from .._discrete_gradient import (
    avf,
    check_points,
    gonzalez,
    gonzalez_values,
    itoh_abe,
    midpoint_gradient,
    with_start_value,
    swap_arguments,
    SwappedArguments,
)
from .._linalg import product
from .._system import SkewGradientSystem
from .base import AbstractMethod, increment_scale, resolution_of


def midpoint_structure(structure, x, x1, args):
    r"""$\tilde\Pi(x, x') = \Pi(\tfrac{x + x'}{2})$: symmetric, so with a symmetric
    discrete gradient the method is time-symmetric and second order (paper §3.2)."""
    check_points("midpoint_structure", x, x1)
    return structure(0.5 * (x + x1), args)


def averaged_structure(structure, x, x1, args):
    r"""$\tilde\Pi(x, x') = \tfrac12(\Pi(x) + \Pi(x'))$: also symmetric and skew."""
    check_points("averaged_structure", x, x1)
    return 0.5 * (structure(x, args) + structure(x1, args))


def _underlying(function):
    """The function behind `functools.partial`s and swapped arguments."""
    while isinstance(function, (functools.partial, SwappedArguments)):
        function = function.func if isinstance(function, functools.partial) else function.function
    return function


class _StepData(NamedTuple):
    """What the residual of one step needs (`DiscreteGradient.setup`): the start $x$,
    the step $h$, the scale $s$ of the unknowns $u = (x' - x)/s$, the time of the
    step's midpoint, at which a force is evaluated, and for `nhjax.gonzalez` $H(x)$,
    which its every iterate needs (`None` otherwise)."""

    system: SkewGradientSystem
    x: Any
    h: Any
    scale: Any
    args: Any
    midpoint_time: Any
    energy: Any = None


class DiscreteGradient(AbstractMethod):
    r"""Energy-preserving discrete-gradient method, eq. (E-int):

    $$\frac{x' - x}{h} = \tilde\Pi(x, x')\, \bar\nabla H(x, x').$$

    $H(x') = H(x)$ holds to roundoff because $\tilde\Pi$ is skew and
    $\bar\nabla H^T (x' - x) = H(x') - H(x)$ (discGradEn). With a symmetric discrete
    gradient (`nhjax.avf`, `nhjax.gonzalez`) and a symmetric $\tilde\Pi$ (the default
    midpoint) the method is time-symmetric, hence second order; with `nhjax.itoh_abe`
    it is first order. For the reduced equations of a nonholonomic system (dynamical)
    it also keeps the constraints, since the $q$-update lies in $\mathcal{D}$.

    **Dissipation and force.** For $\dot x = (\Pi - R)\nabla H + g(t, x)$ the step is

    $$\frac{x' - x}{h} = \big(\tilde\Pi(x, x') - R(\bar x)\big)\bar\nabla H(x, x')
      + g(t + \tfrac h2, \bar x),\qquad \bar x = \tfrac12(x + x'),$$

    $R$ and $g$ at the step's midpoint in state and time (Celledoni & Høiseth,
    arXiv:1706.08621, §3), and the discrete power balance

    $$H(x') - H(x) = h\,\bar\nabla H^T g(t + \tfrac h2, \bar x)
      - h\,\bar\nabla H^TR(\bar x)\bar\nabla H$$

    holds to roundoff, the two terms being the step's `exchange`: what is dissipated is
    never negative where $R(\bar x)$ is positive semidefinite, and the damped,
    unforced energy never increases. The midpoint keeps the method symmetric, so
    second order for a time-dependent $g$.

    Each step solves for the scaled increment $u = (x' - x)/s$, $s = 1 + |x|$ (elementwise),
    from the explicit Euler predictor, by `root_finder` (default: the chord iteration to
    `64 eps` of the dtype, see `nhjax._solver.base.default_root_finder`).

    **Arguments:**

    - `discrete_gradient`: `dg(f, x, x1, args)`; default `nhjax.gonzalez`.
    - `structure_approximation`: `(structure, x, x1, args) -> (N, N)` skew matrix
        approximating $\Pi$; default `nhjax.midpoint_structure`.
    - `root_finder`: an optimistix root finder, or `None` for the default.
    - `root_find_max_steps`: iterations allowed per step before the step fails, a
        positive int.
    """

    term_structure: ClassVar = SkewGradientSystem

    discrete_gradient: Callable = gonzalez
    structure_approximation: Callable = midpoint_structure
    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = 20

    def __check_init__(self):
        for name, example in (("discrete_gradient", "nhjax.gonzalez"), ("structure_approximation", "nhjax.midpoint_structure")):
            value = getattr(self, name)
            if not callable(value):
                raise ValueError(f"DiscreteGradient: {name} must be a function such as {example}, got {value!r}.")

    def order(self, terms):
        del terms
        return {avf: 2, gonzalez: 2, itoh_abe: 1}.get(
            _underlying(self.discrete_gradient)
        )

    def keeps_energy(self) -> bool:
        return True

    def keeps_constraint(self) -> bool:
        """In adapted coordinates the constraint holds by construction."""
        return True

    def summary(self) -> str:
        name = getattr(_underlying(self.discrete_gradient), "__name__", "a user's discrete gradient")
        return f"DiscreteGradient({name}) on the reduced equations in adapted coordinates"

    def is_symmetric(self) -> bool:
        r"""True for the symmetric discrete gradients (`nhjax.avf`, `nhjax.gonzalez`,
        $\bar\nabla H(x', x) = \bar\nabla H(x, x')$) with a symmetric $\tilde\Pi$
        (`midpoint_structure`, `averaged_structure`); False otherwise, including
        user-supplied functions whose symmetry nhjax cannot know."""
        return _underlying(self.discrete_gradient) in (avf, gonzalez) and _underlying(
            self.structure_approximation
        ) in (midpoint_structure, averaged_structure)

    def adjoint(self) -> "DiscreteGradient":
        r"""The adjoint method $\Phi^*_h = \Phi_{-h}^{-1}$: (E-int) with the arguments of
        $\bar\nabla H$ and $\tilde\Pi$ swapped, $(x' - x)/h = \tilde\Pi(x', x)\,
        \bar\nabla H(x', x)$ (solve $\Phi_{-h}(x') = x$ for $x'$), itself a
        discrete-gradient method: $\bar\nabla H(x', x)^T(x' - x) = H(x') - H(x)$.
        `self` when the method is symmetric."""
        if self.is_symmetric():
            return self
        return DiscreteGradient(
            swap_arguments(self.discrete_gradient),
            swap_arguments(self.structure_approximation),
            self.root_finder,
            self.root_find_max_steps,
        )

    def setup(self, system: SkewGradientSystem, t, h, y0, args, carry):
        del carry
        scale = increment_scale(y0)
        midpoint_time = t + 0.5 * h
        guess = h * system.vf(midpoint_time, y0, args) / scale
        energy = system.hamiltonian(y0, args) if self.discrete_gradient is gonzalez else None
        return guess, _StepData(system, y0, h, scale, args, midpoint_time, energy)

    def _equations(self, u, data, discrete_gradient=None, fused=False):
        r"""The step's right-hand side $(x' - x)/h$, and its exchange (`exchange`).

        `fused` (the chord iteration's residual): $\tilde\Pi\,\bar\nabla H$ as a
        broadcast product (`nhjax._linalg.product`), which XLA:CPU fuses with the
        forming of $\tilde\Pi$, so that no $N \times N$ array is left in the
        iteration's loop: one of more than 512 bytes ($N = 13$ on the quartic's adapted
        form) puts every operation of the loop on XLA's thread pool
        (`nhjax._linalg.SEQUENTIAL_BYTES`). Not in the residual that is differentiated
        (the chord matrix, the implicit function theorem): its tangents through the
        broadcast fuse into one large reduction, which cost AVF's step more than the
        loop gained (`python benchmarks/discrete_gradient.py`)."""
        system, x, args = data.system, data.x, data.args
        x1 = x + data.scale * u
        discrete_gradient = self.discrete_gradient if discrete_gradient is None else discrete_gradient
        discrete_gradient = with_start_value(discrete_gradient, data.energy)
        structure = self.structure_approximation(system.structure, x, x1, args)
        gradient = discrete_gradient(system.hamiltonian, x, x1, args)
        field = product(structure, gradient) if fused else structure @ gradient
        if not system.is_forced():
            return field, None
        midpoint, time = 0.5 * (x + x1), data.midpoint_time
        supplied, dissipated = system.power_along(time, midpoint, gradient, args)
        return field + system.applied_force(time, midpoint, args, gradient), (data.h * supplied, data.h * dissipated)

    def residual(self, u, data, discrete_gradient=None, fused=False):
        field, _ = self._equations(u, data, discrete_gradient, fused)
        return u - data.h * field / data.scale

    def residual_and_exchange(self, u, data):
        field, exchange = self._equations(u, data)
        return u - data.h * field / data.scale, exchange

    def exchange(self, u, data):
        r"""$h\,\bar\nabla H^Tg$ and $h\,\bar\nabla H^TR\bar\nabla H$ (see the
        class docstring)."""
        return self._equations(u, data)[1]

    def root_find_residual(self, u, data):
        """The residual with its product fused (`_equations`), and for `nhjax.gonzalez`
        with `gonzalez_values` (the same values, no branch)."""
        values = gonzalez_values if self.discrete_gradient is gonzalez else None
        return self.residual(u, data, values, fused=True)

    def simplified_residual(self, u, data):
        r"""For the symmetric discrete gradients, the residual with the midpoint gradient
        $\nabla H(\bar x)$, which needs no third derivatives of $H$ in the chord matrix
        (see `nhjax._solver.chord`). Both differ from it by $O(|\delta|^2)$: Gonzalez's
        by its correction term, AVF's by its quadrature,
        $\int_0^1\nabla H(x + \tau\delta)\,d\tau = \nabla H(\bar x)
        + \tfrac1{24}\nabla^3H(\bar x)[\delta, \delta] + O(|\delta|^4)$, so the Jacobians
        in $x'$ differ by $O(|\delta|)$ and the residuals' by $O(h|\delta|)$. For AVF this
        drops the Hessian's derivative at every quadrature node from the matrix, for
        a few tenths of an iteration more per step (`python
        benchmarks/discrete_gradient.py` times both). For other discrete gradients
        (Itoh--Abe's, a user's), the residual itself."""
        if _underlying(self.discrete_gradient) not in (gonzalez, avf):
            return self.residual(u, data)
        return self.residual(u, data, midpoint_gradient)

    def resolution(self, data):
        return resolution_of(data.x, data.scale), data.scale

    def complete(self, u, data):
        return data.x + data.scale * u, None
