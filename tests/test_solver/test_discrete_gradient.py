"""The DiscreteGradient method: energy to roundoff, order, time-symmetry, pluggable parts."""

import functools

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import nhjax as nh

from ..helpers import final_state_errors, fitted_order, reference_final_state, relative_energy_error


EXAMPLES = {
    "rolling_disk": (nh.examples.rolling_disk(), lambda e: e.initial_state()),
    "chaplygin_sleigh": (nh.examples.chaplygin_sleigh(), lambda e: e.initial_state(rho1=0.3)),
    "suslov": (nh.examples.suslov(), lambda e: e.initial_state()),
    "chaotic_quartic": (nh.examples.chaotic_quartic(), lambda e: e.initial_state(0.7)),
}


@pytest.mark.parametrize("name", EXAMPLES)
def test_energy_conserved_to_roundoff_over_ten_thousand_steps(name):
    example, initial = EXAMPLES[name]
    solution = nh.integrate(
        example.adapted, nh.DiscreteGradient(), initial(example), 0.1, 10_000, args=example.args
    )
    assert solution.result == nh.RESULTS.successful
    assert relative_energy_error(solution) <= 1e-13


def _one_step(method, system, t0, t1, y, args):
    state = method.init(system, t0, t1, y, args)
    y1, _, _, _, result = method.step(system, t0, t1, y, args, state, False)
    assert result == diffrax.RESULTS.successful
    return y1


@pytest.mark.parametrize(
    "discrete_gradient, symmetric",
    [(nh.gonzalez, True), (nh.avf, True), (nh.itoh_abe, False)],
    ids=["gonzalez", "avf", "itoh_abe"],
)
def test_time_symmetry(discrete_gradient, symmetric):
    """A step with h then one with -h returns the start for symmetric discrete
    gradients, and visibly does not for Itoh-Abe (a control on the test)."""
    quartic = nh.examples.chaotic_quartic()
    method = nh.DiscreteGradient(discrete_gradient)
    system, x0 = quartic.adapted, quartic.initial_state(1.3)
    x1 = _one_step(method, system, 0.0, 0.2, x0, None)
    back = _one_step(method, system, 0.2, 0.0, x1, None)
    distance = float(jnp.max(jnp.abs(back - x0)))
    if symmetric:
        assert distance <= 1e-14
    else:
        assert distance > 1e-6


def _quartic_errors(method, step_sizes, t1=10.0):
    quartic = nh.examples.chaotic_quartic()
    x0 = quartic.initial_state(0.4)
    reference = jnp.concatenate(reference_final_state(quartic.canonical, quartic.from_adapted(x0), t1))
    canonical = lambda x: jnp.concatenate(quartic.from_adapted(x))  # noqa: E731
    return final_state_errors(quartic.adapted, method, x0, t1, step_sizes, reference, observe=canonical)


@pytest.mark.parametrize("discrete_gradient", [nh.gonzalez, nh.avf], ids=["gonzalez", "avf"])
def test_second_order_on_the_quartic_against_an_independent_reference(discrete_gradient):
    step_sizes = [0.1, 0.05, 0.025]
    errors = _quartic_errors(nh.DiscreteGradient(discrete_gradient), step_sizes)
    assert 1.9 <= fitted_order(step_sizes, errors) <= 2.1
    assert errors[-1] < 1e-2


def test_itoh_abe_is_first_order_on_the_quartic():
    step_sizes = [0.05, 0.025, 0.0125]
    errors = _quartic_errors(nh.DiscreteGradient(nh.itoh_abe), step_sizes)
    assert 0.85 <= fitted_order(step_sizes, errors) <= 1.15


def test_second_order_on_the_rolling_disk_against_its_exact_solution():
    disk = nh.examples.rolling_disk()
    x0 = disk.initial_state(x1=0.3, theta=0.2, rho1=1.5, rho2=0.7)
    exact = disk.exact_solution(10.0, x0)
    step_sizes = [0.2, 0.1, 0.05, 0.025]
    errors = final_state_errors(disk.adapted, nh.DiscreteGradient(), x0, 10.0, step_sizes, exact, args=disk.args)
    assert 1.95 <= fitted_order(step_sizes, errors) <= 2.05


def test_structure_approximation_is_pluggable():
    """The averaged structure is another symmetric skew choice: energy still exact and
    the step differs from the midpoint one."""
    quartic = nh.examples.chaotic_quartic()
    x0 = quartic.initial_state(2.0)
    averaged = nh.DiscreteGradient(structure_approximation=nh.averaged_structure)
    sol_avg = nh.integrate(quartic.adapted, averaged, x0, 0.1, 1000)
    sol_mid = nh.integrate(quartic.adapted, nh.DiscreteGradient(), x0, 0.1, 1000)
    assert relative_energy_error(sol_avg) <= 1e-13
    assert float(jnp.max(jnp.abs(sol_avg.ys[-1] - sol_mid.ys[-1]))) > 1e-6
    # A name where the function goes is named when the method is made, not in its step.
    with pytest.raises(ValueError, match="structure_approximation must be a function such as nhjax.midpoint_structure"):
        nh.DiscreteGradient(structure_approximation="averaged")
    with pytest.raises(ValueError, match="discrete_gradient must be a function such as nhjax.gonzalez, got 'avf'"):
        nh.DiscreteGradient(discrete_gradient="avf")


@pytest.mark.parametrize("discrete_gradient", [nh.gonzalez, nh.avf])
def test_custom_root_finder_is_used_and_finds_the_same_root(discrete_gradient):
    """optimistix's Newton (exact Jacobian at every iterate) against the default chord
    iteration (the Jacobian of the midpoint-gradient residual, once per step): the same
    trajectory, Newton in fewer iterations."""
    quartic = nh.examples.chaotic_quartic()
    x0 = quartic.initial_state(2.0)
    newton = nh.DiscreteGradient(discrete_gradient, root_finder=optx.Newton(rtol=0.0, atol=1e-14))
    solution = nh.integrate(quartic.adapted, newton, x0, 0.1, 200)
    chord = nh.integrate(quartic.adapted, nh.DiscreteGradient(discrete_gradient), x0, 0.1, 200)
    assert relative_energy_error(solution) <= 1e-13
    np.testing.assert_allclose(solution.ys, chord.ys, atol=1e-13)
    assert int(solution.stats["root_find_steps"]) < int(chord.stats["root_find_steps"])


@pytest.mark.parametrize("discrete_gradient", [nh.gonzalez, nh.avf])
def test_the_chord_matrix_differs_from_the_residuals_jacobian_at_second_order(discrete_gradient):
    """The chord matrix, from the midpoint gradient, against the Jacobian of the
    residual itself (the discrete gradient's correction or quadrature differentiated) at
    the step's predictor on the quartic's adapted form: apart by O(h |delta|) = O(h^2),
    not equal."""
    quartic = nh.examples.chaotic_quartic()
    x0 = quartic.initial_state(0.7)
    method = nh.DiscreteGradient(discrete_gradient)
    step_sizes, gaps = [0.1, 0.05, 0.025], []
    for h in step_sizes:
        guess, data = method.setup(quartic.adapted, 0.0, h, x0, None, method.initial_carry(quartic.adapted, x0, None))
        chord = jax.jacfwd(method.simplified_residual)(guess, data)
        exact = jax.jacfwd(method.residual)(guess, data)
        gaps.append(float(jnp.max(jnp.abs(chord - exact))))
    assert gaps[0] > 1e-6, gaps
    assert 1.7 <= fitted_order(step_sizes, gaps) <= 2.5, gaps


def test_float32_conserves_energy_to_float32_roundoff():
    quartic = nh.examples.chaotic_quartic()
    x0 = quartic.initial_state(0.7, dtype=jnp.float32)
    solution = nh.integrate(quartic.adapted, nh.DiscreteGradient(), x0, 0.1, 1000)
    assert solution.ys.dtype == jnp.float32 and solution.energy.dtype == jnp.float32
    assert solution.result == nh.RESULTS.successful
    assert relative_energy_error(solution) <= 100 * float(jnp.finfo(jnp.float32).eps)


def test_order_reported_to_diffrax():
    assert nh.DiscreteGradient().order(None) == 2
    assert nh.DiscreteGradient(functools.partial(nh.avf, nodes=4)).order(None) == 2
    assert nh.DiscreteGradient(nh.itoh_abe).order(None) == 1


def test_diffeqsolve_drives_the_method_directly():
    sleigh = nh.examples.chaplygin_sleigh()
    x0 = sleigh.initial_state(rho1=0.3)
    ours = nh.integrate(sleigh.adapted, nh.DiscreteGradient(), x0, 0.5, 40, args=sleigh.args)
    theirs = diffrax.diffeqsolve(
        sleigh.adapted, nh.DiscreteGradient(), 0.0, 20.0, 0.5, x0, args=sleigh.args,
        saveat=diffrax.SaveAt(t1=True),
    )
    np.testing.assert_allclose(theirs.ys[-1], ours.ys[-1], rtol=1e-12, atol=1e-13)
