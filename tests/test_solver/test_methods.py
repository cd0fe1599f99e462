"""What every method for NonholonomicSystems shares, tested once over the methods of
`tests/helpers.py` on the paper's systems: order 2 against the index-1 reference,
energy and constraint to roundoff where the method keeps them (and visibly not where it
does not), and time symmetry (a step with h, then one with -h, returns to the start).

Each (method, start) is one compiled run: 10^4 steps at each of the step sizes 0.2,
0.1, 0.05 together (`jax.vmap` over dt), every step saved; the order is read at t = 5
and the invariants over the whole run. These runs are long enough that compiling them at
XLA's full optimisation (`helpers.FULL_OPTIMISATION`) costs less than it saves in
running them."""

import functools

import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import nhjax as nh

from ..helpers import (
    CANONICAL_METHODS,
    canonical_starts,
    errors_at,
    fitted_order,
    FULL_OPTIMISATION,
    KEEPS_CONSTRAINT,
    KEEPS_ENERGY,
    METHODS,
    reference_final_state,
    runs_at_step_sizes,
    step_there_and_back,
)


STARTS = canonical_starts()
STEP_SIZES = (0.2, 0.1, 0.05)
N_STEPS = 10_000
T1 = 5.0
CASES = [(method, start) for method in CANONICAL_METHODS for start in STARTS]
# The higher-order methods' orders are fitted in their own tests, at step sizes that
# keep their errors above the reference's.
SECOND_ORDER_CASES = [(method, start) for method, start in CASES if METHODS[method].order(None) == 2]


@functools.cache
def _runs(method, start):
    example, y0 = STARTS[start]
    return runs_at_step_sizes(
        example.canonical, METHODS[method], y0, STEP_SIZES, N_STEPS, example.args, compiler_options=FULL_OPTIMISATION
    )


@functools.cache
def _reference(start):
    example, y0 = STARTS[start]
    return reference_final_state(example.canonical, y0, T1, example.args)


@pytest.mark.parametrize("method, start", SECOND_ORDER_CASES)
def test_second_order_against_the_index1_reference(method, start):
    errors = errors_at(_runs(method, start), STEP_SIZES, T1, _reference(start))
    assert 1.8 <= fitted_order(STEP_SIZES, errors) <= 2.2, errors


@pytest.mark.parametrize("method, start", CASES)
def test_invariants_over_ten_thousand_steps(method, start):
    """Energy to roundoff at every step size if the method keeps it; otherwise, at
    h = 0.05, an error far above roundoff that stays small, except on the disk, whose
    energy the symmetric DLA and SPARK methods keep to roundoff as well (2e-15 measured),
    which is allowed, not required. The constraint A(q) dH/dp = 0 to roundoff at every
    step size if the method keeps it, otherwise visibly violated, within O(h^2)."""
    solutions = _runs(method, start)
    assert bool(jnp.all(solutions.result == nh.RESULTS.successful))
    energy_error = jnp.max(jnp.abs(solutions.energy / solutions.energy[:, :1] - 1), axis=1)
    violation = jnp.max(jnp.abs(solutions.constraint), axis=(1, 2))
    if method in KEEPS_ENERGY:
        assert float(jnp.max(energy_error)) <= 1e-13, energy_error
    else:
        smallest_step = float(energy_error[STEP_SIZES.index(0.05)])
        assert smallest_step < 1e-2, energy_error
        assert start.startswith("disk") or smallest_step > 1e-10, energy_error
    if method in KEEPS_CONSTRAINT:
        assert float(jnp.max(violation)) <= 1e-13, violation
    else:
        assert bool(jnp.all((1e-6 < violation) & (violation < 1e-1))), violation


@pytest.mark.parametrize("method, start", CASES)
def test_time_symmetric(method, start):
    example, y0 = STARTS[start]
    there_and_back = eqx.filter_jit(step_there_and_back)
    back, results = there_and_back(example.canonical, METHODS[method], y0, 0.2, example.args)
    assert all(result == diffrax.RESULTS.successful for result in results)
    np.testing.assert_allclose(back[0], y0[0], rtol=0, atol=1e-14)
    np.testing.assert_allclose(back[1], y0[1], rtol=0, atol=1e-14)


QUARTIC = nh.examples.chaotic_quartic()


@pytest.mark.parametrize("method", METHODS)
def test_bad_root_finders_and_a_system_of_another_kind_are_named(method):
    """A method refuses a root-finder budget that is not a positive int (with none, a
    run reported every unsolved step as a non-finite state) and a root finder that is
    not an optimistix root finder when it is made, and a run refuses a system of
    another kind than the method integrates (its `term_structure`) before any step: a
    method for skew-gradient systems given one in canonical coordinates failed inside
    its first step, on the tuple (q, p)."""
    kind = type(METHODS[method])
    for budget in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match=f"{kind.__name__}: root_find_max_steps must be a positive int"):
            kind(root_find_max_steps=budget)
    for finder in ("newton", optx.BFGS(rtol=1e-8, atol=1e-8)):
        with pytest.raises(ValueError, match=f"{kind.__name__}: root_finder must be None .* or an optimistix root finder"):
            kind(root_finder=finder)
    assert kind(root_finder=optx.Newton(rtol=1e-10, atol=1e-10)).root_finder is not None
    wants = METHODS[method].term_structure
    if wants is nh.SkewGradientSystem:
        system, y0, hint = QUARTIC.canonical, QUARTIC.start("canonical"), r" Its reduced form, system\.reduced"
    elif wants is nh.NonholonomicSystem:
        system, y0, hint = QUARTIC.adapted, QUARTIC.start("adapted"), ""
    else:
        assert wants is nh.AbstractSystem  # the collocation: both kinds
        return
    with pytest.raises(ValueError, match=f"integrates a {wants.__name__}, got a {type(system).__name__}.{hint}"):
        nh.integrate(system, METHODS[method], y0, 0.1, 3)
    if METHODS[method].composition_obstacle() is None:
        with pytest.raises(ValueError, match=f"integrates a {wants.__name__}"):
            nh.integrate(system, nh.Composition(METHODS[method], order=4), y0, 0.1, 3)
