"""What every example of the catalogue says about itself holds: its forms describe one
system, its start is on the constraint in each, its parameters make it again."""

import jax
import numpy as np
import pytest

import nhjax as nh


EXAMPLES = nh.examples.EXAMPLES


def _dependent_on_constraint(example, q, p):
    """A(q) M(q)^{-1} p by autodiff of the canonical H: zero on the constraint."""
    velocity = jax.grad(example.canonical.hamiltonian, argnums=1)(q, p, example.args)
    return example.canonical.constraints(q, example.args) @ velocity


@pytest.mark.parametrize("name", EXAMPLES)
def test_the_forms_agree_at_the_start(name):
    """The start in each form has the same energy, the canonical and Lagrangian forms
    read the same (q, p), the canonical start is on the constraint, and the adapted
    coordinates map there and back."""
    example = EXAMPLES[name]()
    assert example.name == name and example.forms()
    energies = {form: float(example.system(form).energy(example.start(form), example.args)) for form in example.forms()}
    reference = next(iter(energies.values()))
    for form, energy in energies.items():
        assert abs(energy - reference) <= 1e-14 * max(1.0, abs(reference)), (form, energies)
    if "canonical" in example.forms():
        q, p = example.start("canonical")
        assert float(np.max(np.abs(_dependent_on_constraint(example, q, p)))) < 1e-14
        if "lagrangian" in example.forms():
            np.testing.assert_array_equal(example.start("lagrangian")[1], p)
    if {"canonical", "adapted"} <= set(example.forms()):
        x = example.start("adapted")
        np.testing.assert_allclose(example.to_adapted(*example.from_adapted(x)), x, rtol=0, atol=1e-15)


@pytest.mark.parametrize("name", EXAMPLES)
def test_the_parameters_make_the_example_again(name):
    example = EXAMPLES[name]()
    again = type(example)(**example.parameters())
    assert again.args == example.args and again.forms() == example.forms()
    # Every parameter the system's functions read is a parameter of the example.
    assert set(example.args or {}) <= set(example.parameters())
    # A changed start choice changes the start: the choices reach it.
    choices = example.initial_state_choices()
    assert choices, "an example names the choices of its start"
    first = next(iter(choices))
    changed = example.initial_state(**{first: choices[first] + 1})
    assert not np.array_equal(np.concatenate(jax.tree.leaves(changed)), np.concatenate(jax.tree.leaves(example.initial_state())))


@pytest.mark.parametrize("name", EXAMPLES)
def test_a_parameter_that_is_not_a_finite_number_is_named(name):
    """Every parameter of every example refuses NaN and a string when the example is
    made, naming itself (the contact oscillator took both, and the others' string was
    refused by float() without the parameter's name)."""
    factory = EXAMPLES[name]
    for parameter in factory().parameters():
        for bad in (float("nan"), "0.5"):
            with pytest.raises(ValueError, match=parameter):
                factory(**{parameter: bad})


def test_a_missing_form_is_named():
    with pytest.raises(ValueError, match="The suslov example has no canonical form; it has adapted"):
        nh.examples.suslov().start("canonical")
    with pytest.raises(ValueError, match="The gearbox example has no adapted form"):
        nh.examples.gearbox().system("adapted")
    with pytest.raises(ValueError, match="Unknown form 'reduced'"):
        nh.examples.gearbox().system("reduced")


def test_random_starts_where_an_example_draws_them():
    for name, example in EXAMPLES.items():
        example = example()
        if not example.has_random_states():
            with pytest.raises(NotImplementedError, match="no random initial states"):
                example.random_initial_state(jax.random.key(0))
            continue
        first, second = (example.start("canonical", key=jax.random.key(seed)) for seed in (0, 1))
        assert not np.array_equal(first[0], second[0])
        assert float(np.max(np.abs(_dependent_on_constraint(example, *first)))) < 1e-14
