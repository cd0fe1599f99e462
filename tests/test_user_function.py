"""A system's functions are traced once per program (`nhjax._user_function`)."""

import jax
import jax.numpy as jnp

import nhjax as nh


SLEIGH = nh.examples.chaplygin_sleigh()


def _counting_sleigh():
    """The sleigh's canonical form, with H and A that count how often their Python
    bodies run."""
    calls = dict(hamiltonian=0, constraints=0)
    canonical = SLEIGH.canonical

    def hamiltonian(q, p, args):
        calls["hamiltonian"] += 1
        return canonical.hamiltonian(q, p, args)

    def constraints(q, args):
        calls["constraints"] += 1
        return canonical.constraints(q, args)

    return nh.NonholonomicSystem(hamiltonian, constraints), calls


def test_a_run_traces_the_users_functions_a_few_times_not_once_per_call():
    """GONZALEZ-R's step evaluates and differentiates H and A at many points (the plain
    functions ran 29 and 31 times while one run was traced); each runs once per kind of
    call here (shapes, and the dtype of what it is called with)."""
    system, calls = _counting_sleigh()
    y0 = SLEIGH.from_adapted(jnp.array([0.0, 0.0, 0.1, 0.3, -0.6]), SLEIGH.args)
    jax.jit(lambda y: nh.integrate(system, nh.GonzalezR(), y, 0.1, 10, args=SLEIGH.args)).trace(y0)
    assert 1 <= calls["hamiltonian"] <= 4, calls
    assert 1 <= calls["constraints"] <= 4, calls


def test_systems_of_the_same_functions_are_equal_and_not_wrapped_twice():
    canonical = SLEIGH.canonical
    a = nh.NonholonomicSystem(canonical.hamiltonian, canonical.constraints)
    b = nh.NonholonomicSystem(canonical.hamiltonian, canonical.constraints)
    assert a == b and hash(a) == hash(b)
    assert nh.NonholonomicSystem(a.hamiltonian, a.constraints) == a  # not wrapped twice
