"""The methods by name, one registry for the command line, the experiments and the
tests: each with the paper's name and a colour for the figures. What a method keeps, its
order, whether it is symmetric and the form of the system it integrates are the method's
own to say (`keeps_energy()`, `keeps_constraint()`, `order(terms)`, `is_symmetric()`,
`term_structure`); for the diffrax solvers beside them, which keep nothing, the functions
here answer."""

import functools
from collections.abc import Callable
from typing import NamedTuple

import diffrax

from ._discrete_gradient import avf, gonzalez
from ._solver import DiscreteGradient, EnergyPreservingCollocation, GonzalezF, GonzalezR, IDLA, Projection, SIDLA, SPARK
from ._system import AbstractSystem, SkewGradientSystem


# For a method registered without a colour of its own.
DEFAULT_COLOUR = "0.4"


def integrates_adapted(solver: diffrax.AbstractSolver) -> bool:
    """Whether `solver` integrates an example's reduced equations in adapted coordinates
    (a `SkewGradientSystem`) rather than a `NonholonomicSystem` in canonical ones."""
    return getattr(solver, "term_structure", None) is SkewGradientSystem


def takes_either_form(solver: diffrax.AbstractSolver) -> bool:
    """Whether `solver` integrates both forms, canonical and adapted (its
    `term_structure` is any `AbstractSystem`); the registry takes it for a canonical
    method, and the command line gives it the adapted form of an example that has no
    other."""
    return getattr(solver, "term_structure", None) is AbstractSystem


def keeps_energy(solver: diffrax.AbstractSolver) -> bool:
    return getattr(solver, "keeps_energy", lambda: False)()


def keeps_constraint(solver: diffrax.AbstractSolver) -> bool:
    return getattr(solver, "keeps_constraint", lambda: False)()


def is_symmetric(solver: diffrax.AbstractSolver) -> bool:
    """Whether `solver` is its own adjoint; the explicit Runge-Kutta methods are not."""
    return getattr(solver, "is_symmetric", lambda: False)()


def description(solver: diffrax.AbstractSolver) -> str:
    """A line on what `solver` is, its order and what it keeps, from the solver itself."""
    summary = getattr(solver, "summary", None)
    summary = summary() if summary else f"{type(solver).__name__} (diffrax) at fixed steps on the index-1 ODE"
    order = solver.order(None)
    energy, constraint = keeps_energy(solver), keeps_constraint(solver)
    if energy and constraint:
        kept = (
            "energy to roundoff, the constraint by construction"
            if integrates_adapted(solver)
            else "energy and constraint to roundoff"
        )
    elif energy:
        kept = "energy to roundoff, the constraint not"
    elif constraint:
        kept = f"constraint to roundoff, energy O(h^{order})"
    else:
        kept = "neither energy nor constraint"
    symmetric = "symmetric" if is_symmetric(solver) else "not symmetric"
    return f"{summary}: order {order}, {symmetric}, {kept}"


class Method(NamedTuple):
    """A method as the paper names it (`name`), made with its defaults by `make` (when
    it is asked for, so that nothing is built before the caller has chosen its dtype),
    and drawn in `colour`."""

    name: str
    make: Callable[[], diffrax.AbstractSolver]
    colour: str = DEFAULT_COLOUR

    @property
    def solver(self) -> diffrax.AbstractSolver:
        return self.make()

    @property
    def adapted(self) -> bool:
        return integrates_adapted(self.solver)

    @property
    def keeps_energy(self) -> bool:
        return keeps_energy(self.solver)

    @property
    def keeps_constraint(self) -> bool:
        return keeps_constraint(self.solver)

    @property
    def description(self) -> str:
        return description(self.solver)


METHODS = {
    "gonzalez-r": Method("GONZALEZ-R", GonzalezR, "C0"),
    "gonzalez-f": Method("GONZALEZ-F", GonzalezF, "C1"),
    "sidla": Method("SI-DLA", SIDLA, "C2"),
    "idla": Method("I-DLA", IDLA, "C3"),
    "spark": Method("SPARK", SPARK, "C4"),
    "avf": Method("AVF", functools.partial(DiscreteGradient, discrete_gradient=avf), "C5"),
    "gonzalez": Method("GONZALEZ", functools.partial(DiscreteGradient, discrete_gradient=gonzalez), "C6"),
    "ep-collocation-4": Method("EP-COLLOCATION 4", functools.partial(EnergyPreservingCollocation, order=4), "firebrick"),
    "ep-collocation-6": Method("EP-COLLOCATION 6", functools.partial(EnergyPreservingCollocation, order=6), "darkgoldenrod"),
    "dopri8-projection": Method("Dopri8 + projection", lambda: Projection(diffrax.Dopri8()), "olive"),
    "tsit5": Method("Tsit5", diffrax.Tsit5, "C7"),
}
