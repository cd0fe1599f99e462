"""The methods by name, one registry for the command line, the experiments and the
tests: each with the paper's name, the form of the system it integrates, and what it
keeps to roundoff."""

import functools
from collections.abc import Callable
from typing import NamedTuple

import diffrax

from ._discrete_gradient import avf, gonzalez
from ._solver import DiscreteGradient, GonzalezF, GonzalezR, IDLA, Projection, SIDLA, SPARK


class Method(NamedTuple):
    """A method as the paper names it (`name`). `adapted`: it integrates an example's
    reduced equations in adapted coordinates (a `SkewGradientSystem`), not the
    canonical `NonholonomicSystem`. `keeps_energy`, `keeps_constraint`: to roundoff, at
    every step. `description`: one line on what it is and what it keeps. `solver` makes
    the method with its defaults (when it is asked for, so that nothing is built before
    the caller has chosen its dtype)."""

    name: str
    make: Callable[[], diffrax.AbstractSolver]
    adapted: bool
    keeps_energy: bool
    keeps_constraint: bool
    description: str

    @property
    def solver(self) -> diffrax.AbstractSolver:
        return self.make()


METHODS = {
    "gonzalez-r": Method(
        "GONZALEZ-R", GonzalezR,
        adapted=False, keeps_energy=True, keeps_constraint=True,
        description="§3.3, the discrete gradient on the reduced system in canonical coordinates: "
        "energy and constraint to roundoff",
    ),
    "gonzalez-f": Method(
        "GONZALEZ-F", GonzalezF,
        adapted=False, keeps_energy=True, keeps_constraint=False,
        description="§3.3, the direct method in canonical coordinates: energy to roundoff, the constraint not",
    ),
    "sidla": Method(
        "SI-DLA", SIDLA,
        adapted=False, keeps_energy=False, keeps_constraint=True,
        description="McLachlan & Perlmutter's semi-implicit DLA in canonical coordinates: constraint to "
        "roundoff, energy O(h^2)",
    ),
    "idla": Method(
        "I-DLA", IDLA,
        adapted=False, keeps_energy=False, keeps_constraint=True,
        description="the implicit DLA with the midpoint discrete Lagrangian and the constraint impulses at "
        "the step's ends, in canonical coordinates: constraint to roundoff, energy O(h^2)",
    ),
    "spark": Method(
        "SPARK", SPARK,
        adapted=False, keeps_energy=False, keeps_constraint=True,
        description="2-stage Lobatto SPARK (Jay's IIIA-B-C-C*-D family: IIIA for the velocity, IIIB for "
        "every force, the constraint force included) in canonical coordinates: constraint to roundoff, "
        "energy O(h^2)",
    ),
    "avf": Method(
        "AVF", functools.partial(DiscreteGradient, discrete_gradient=avf),
        adapted=True, keeps_energy=True, keeps_constraint=True,
        description="DiscreteGradient(avf) on the reduced equations in adapted coordinates: energy to "
        "roundoff, the constraint by construction",
    ),
    "gonzalez": Method(
        "GONZALEZ", functools.partial(DiscreteGradient, discrete_gradient=gonzalez),
        adapted=True, keeps_energy=True, keeps_constraint=True,
        description="DiscreteGradient(gonzalez) on the reduced equations in adapted coordinates: energy to "
        "roundoff, the constraint by construction",
    ),
    "dopri8-projection": Method(
        "Dopri8 + projection", lambda: Projection(diffrax.Dopri8()),
        adapted=False, keeps_energy=True, keeps_constraint=True,
        description="Dopri8 at fixed steps on the index-1 ODE, each step's end projected onto the energy "
        "level and the constraint: order 8, energy and constraint to roundoff, not symmetric",
    ),
    "tsit5": Method(
        "Tsit5", diffrax.Tsit5,
        adapted=False, keeps_energy=False, keeps_constraint=False,
        description="Tsit5 at fixed steps on the index-1 ODE: the non-geometric baseline",
    ),
}
