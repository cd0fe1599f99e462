"""What every example says about itself: its name, its parameters, the forms it comes
in and its initial states, in one convention."""

import dataclasses
import inspect
from typing import Any, ClassVar

import equinox as eqx
from jaxtyping import Array, PRNGKeyArray

from .._nonholonomic import NonholonomicSystem
from .._system import AbstractSystem, SkewGradientSystem


# The forms an example may come in, each a property of the example:
# - "canonical": a `NonholonomicSystem` in $(q, p)$ with $H$ written out;
# - "lagrangian": the same system from its Lagrangian (`NonholonomicSystem.from_lagrangian`), in $(q, p)$;
# - "adapted": the reduced equations (dynamical), a `SkewGradientSystem` in $x = (q, \rho)$.
FORMS = {"canonical": "canonical", "lagrangian": "canonical_from_lagrangian", "adapted": "adapted"}


class AbstractExample(eqx.Module):
    r"""A system nhjax simulates, with what describes it.

    - `name` (a class attribute) names it on the command line and in the catalogue
      `nhjax.examples.EXAMPLES`; `title` says in a line what it is and where it comes
      from.
    - Its fields are its parameters (`parameters()`). Those that the system's functions
      read are passed as `args` (a dict, or `None` where there are none); static ones
      (such as the chaotic quartic's size `n`) shape the system itself.
    - Its forms (`forms()`, `system(form)`): the properties `canonical`,
      `canonical_from_lagrangian` and `adapted` that it has (the others are `None`).
    - **Initial states, one convention.** `initial_state(...)` returns the state in
      adapted coordinates $x = (q, \rho)$ where the example has them (its parameters are
      the paper's: $\rho$ is what its figures start from), in canonical coordinates
      $(q, p)$ otherwise; its defaults are the example's usual start. `start(form, ...)`
      gives that state in any of the example's forms, through `from_adapted`.
    - Examples with a family of generic starts draw one with `random_initial_state(key)`
      (`has_random_states()`).
    """

    name: ClassVar[str]
    title: ClassVar[str]

    @property
    def args(self) -> dict[str, Any] | None:
        """The parameters the system's functions read: every field that is not static."""
        values = {
            field.name: getattr(self, field.name)
            for field in dataclasses.fields(self)
            if not field.metadata.get("static", False)
        }
        return values or None

    def parameters(self) -> dict[str, Any]:
        """Every parameter, static ones included: `type(example)(**example.parameters())`
        is the same example."""
        return {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}

    @property
    def canonical(self) -> NonholonomicSystem | None:
        return None

    @property
    def canonical_from_lagrangian(self) -> NonholonomicSystem | None:
        return None

    @property
    def adapted(self) -> SkewGradientSystem | None:
        return None

    def forms(self) -> tuple[str, ...]:
        """The forms this example comes in, of "canonical", "lagrangian", "adapted"."""
        return tuple(form for form, attribute in FORMS.items() if getattr(self, attribute) is not None)

    def system(self, form: str) -> AbstractSystem:
        """The system in `form` (one of `forms()`)."""
        if form not in FORMS:
            raise ValueError(f"Unknown form {form!r}: the forms are {', '.join(FORMS)}.")
        system = getattr(self, FORMS[form])
        if system is None:
            raise ValueError(f"The {self.name} example has no {form} form; it has {', '.join(self.forms())}.")
        return system

    def initial_state(self, *args, **kwargs):
        """The example's usual start with its defaults: adapted coordinates where the
        example has them, $(q, p)$ otherwise."""
        raise NotImplementedError

    def start(self, form: str = "canonical", key: PRNGKeyArray | None = None, **choices):
        """`initial_state(**choices)`, or `random_initial_state(key)` when a key is given,
        in `form`: $(q, p)$ for the canonical and Lagrangian forms, $x = (q, \\rho)$ for
        the adapted one."""
        self.system(form)
        state = self.initial_state(**choices) if key is None else self.random_initial_state(key)
        if self.adapted is None or form == "adapted":
            return state
        return self.from_adapted(state)

    def initial_state_choices(self) -> dict[str, Any]:
        """The keyword arguments of `initial_state` with their defaults (`dtype` aside)."""
        signature = inspect.signature(self.initial_state)
        return {
            name: parameter.default
            for name, parameter in signature.parameters.items()
            if name != "dtype" and parameter.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD
        }

    def has_random_states(self) -> bool:
        return type(self).random_initial_state is not AbstractExample.random_initial_state

    def random_initial_state(self, key: PRNGKeyArray, dtype=None):
        """A generic start drawn with `key`, in the convention of `initial_state`."""
        raise NotImplementedError(f"The {self.name} example has no random initial states.")

    def to_adapted(self, q: Array, p: Array, args=None) -> Array:
        """Canonical to adapted coordinates, $(q, p) \\mapsto (q, X(q)^Tp)$."""
        raise ValueError(f"The {self.name} example has no adapted form.")

    def from_adapted(self, x: Array, args=None) -> tuple[Array, Array]:
        """Adapted to canonical coordinates, the inverse of `to_adapted`."""
        raise ValueError(f"The {self.name} example has no canonical form.")
