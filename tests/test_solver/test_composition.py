"""Symmetric composition: the schemes' orders (on a model of a symmetric method and on
the paper's systems against exact and independent reference solutions), invariants to
roundoff at high order, symmetry, what a wrong scheme does, what is refused, and the
composition everywhere a method goes (vmap, grad, float32, chunked runs, codes)."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import nhjax as nh

from ..helpers import (
    check_float32,
    check_per_trajectory_result_codes,
    errors_at,
    fitted_order,
    relative_energy_error,
    runs_at_step_sizes,
    step_there_and_back,
)


SUSLOV = nh.examples.suslov()
DISK = nh.examples.rolling_disk()
QUARTIC = nh.examples.chaotic_quartic(3)
SLEIGH = nh.examples.chaplygin_sleigh(J=8.0, a=1.0, m=1.0)
GEARBOX = nh.examples.gearbox()
WITHIN = {4: (3.7, 4.6), 6: (5.7, 6.6), 8: (7.7, 8.6)}  # [p - 0.3, p + 0.6]


def _lie_model_errors(coefficients, step_sizes):
    r"""A model of every symmetric second-order method: $\Phi_h = \exp(hA + h^3B +
    h^5C + h^7D)$ with random non-commuting matrices (a symmetric method's modified
    flow has odd powers of $h$ only). The composition's local error
    $\|\Psi_h - \exp(hA)\|$ is $O(h^{p+1})$ for a scheme of order $p$."""
    generator = np.random.default_rng(0)
    a, b, c, d = (generator.standard_normal((4, 4)) for _ in range(4))
    errors = []
    for h in step_sizes:
        composed = np.eye(4)
        for gamma in coefficients:
            k = gamma * h
            composed = scipy.linalg.expm(k * a + k**3 * b + k**5 * c + k**7 * d) @ composed
        errors.append(np.max(np.abs(composed - scipy.linalg.expm(h * a))))
    return errors


@pytest.mark.parametrize("name", list(nh.COMPOSITION_SCHEMES))
def test_every_scheme_has_its_order_on_the_model_of_a_symmetric_method(name):
    scheme = nh.COMPOSITION_SCHEMES[name]
    step_sizes = (0.2, 0.14, 0.1, 0.07)
    low, high = WITHIN[scheme["order"]]
    local_order = fitted_order(step_sizes, _lie_model_errors(scheme["coefficients"], step_sizes))
    assert low + 1 <= local_order <= high + 1, local_order


def _wrong(coefficients):
    """The scheme with its outer pair moved by 1% and the middle one making up the sum:
    still symmetric and consistent, no longer a solution of the order conditions."""
    gamma = list(coefficients)
    shift = 0.01 * gamma[0]
    gamma[0] += shift
    gamma[-1] += shift
    gamma[len(gamma) // 2] -= 2 * shift
    return gamma


def test_a_wrong_scheme_loses_the_order():
    step_sizes = (0.2, 0.14, 0.1, 0.07)
    suzuki = nh.COMPOSITION_SCHEMES["suzuki-4"]["coefficients"]
    assert fitted_order(step_sizes, _lie_model_errors(_wrong(suzuki), step_sizes)) <= 3.3
    # ... and on a system, with the composition accepting it (it is symmetric and sums
    # to 1): second order, where the right scheme has fourth.
    rho0 = SUSLOV.initial_state(omega1=1.0, omega2=0.5)
    wrong = nh.Composition(nh.DiscreteGradient(), 4, coefficients=_wrong(suzuki))
    errors = _errors(SUSLOV.adapted, wrong, rho0, 10.0, (0.5, 0.25, 0.125), SUSLOV.exact_solution(10.0, rho0), SUSLOV.args)
    assert 1.8 <= fitted_order((0.5, 0.25, 0.125), errors) <= 2.3, errors


def _runs(system, method, y0, t1, step_sizes, args=None):
    """`runs_at_step_sizes` with t1 / min(step_sizes) steps at every size; every run must
    succeed."""
    runs = runs_at_step_sizes(system, method, y0, step_sizes, round(t1 / min(step_sizes)), args)
    assert bool(jnp.all(runs.result == nh.RESULTS.successful))
    return runs


def _errors(system, method, y0, t1, step_sizes, reference, args=None, observe=lambda y: y, runs=None):
    """max |observe(y(t1)) - reference| at each step size, from `_runs` (or the given
    `runs` of it)."""
    runs = _runs(system, method, y0, t1, step_sizes, args) if runs is None else runs
    return errors_at(runs, step_sizes, t1, reference, observe)


def _reference(system, y0, t1, args=None):
    """The index-1 ODE (or the reduced equations) by adaptive Dopri8 at 1e-14."""
    solution = nh.integrate_adaptive(system, y0, t1, args, rtol=1e-14, atol=1e-14)
    return jax.tree.map(lambda y: y[-1], solution.ys)


# (what, order): (system, method, initial state, t1, step sizes, reference, args, observe)
def _order_cases():
    rho0 = SUSLOV.initial_state(omega1=1.0, omega2=0.5)
    suslov = (SUSLOV.adapted, nh.DiscreteGradient(), rho0, 10.0, None, lambda: SUSLOV.exact_solution(10.0, rho0), SUSLOV.args)
    x0 = DISK.initial_state(theta=0.2, rho1=1.3, rho2=0.9)
    disk = (DISK.adapted, nh.DiscreteGradient(), x0, 4.0, None, lambda: DISK.exact_solution(4.0, x0), DISK.args)
    xq = QUARTIC.initial_state(0.7)
    quartic = (QUARTIC.adapted, nh.DiscreteGradient(), xq, 2.0, None, lambda: _reference(QUARTIC.adapted, xq, 2.0), None)
    xs = SLEIGH.initial_state(rho1=0.3, rho2=-0.6)
    sleigh = (SLEIGH.adapted, nh.DiscreteGradient(), xs, 12.0, None, lambda: _reference(SLEIGH.adapted, xs, 12.0, SLEIGH.args), SLEIGH.args)
    yg = GEARBOX.random_initial_state(jax.random.key(0))
    gearbox = (GEARBOX.canonical, nh.GonzalezR(), yg, 2.0, None, lambda: _reference(GEARBOX.canonical, yg, 2.0, GEARBOX.args), GEARBOX.args)
    # Step sizes where each error is well above roundoff and in its asymptotic regime.
    sizes = {
        ("suslov, exact", 4): (suslov, (0.5, 0.25, 0.125)),
        ("suslov, exact", 6): (suslov, (1.0, 0.5, 0.25)),
        ("suslov, exact", 8): (suslov, (1.0, 0.625, 0.5)),
        ("disk, exact", 4): (disk, (0.4, 0.2, 0.1)),
        ("disk, exact", 6): (disk, (0.8, 0.4, 0.2)),
        ("disk, exact", 8): (disk, (1.0, 0.5, 0.25)),
        ("quartic, reference", 4): (quartic, (0.1, 0.05, 0.025)),
        ("quartic, reference", 6): (quartic, (0.2, 0.1, 0.05)),
        ("quartic, reference", 8): (quartic, (0.2, 0.125, 0.1)),
        ("sleigh, reference", 4): (sleigh, (0.4, 0.2, 0.1)),
        ("sleigh, reference", 6): (sleigh, (2.0, 1.0, 0.5)),
        ("sleigh, reference", 8): (sleigh, (3.0, 2.0, 1.5)),
        ("gearbox, GONZALEZ-R, reference", 4): (gearbox, (0.4, 0.2, 0.1)),
        ("gearbox, GONZALEZ-R, reference", 6): (gearbox, (0.4, 0.2, 0.1)),
        ("gearbox, GONZALEZ-R, reference", 8): (gearbox, (0.25, 0.2, 0.125)),
    }
    return sizes


_REFERENCES = {}


@pytest.mark.parametrize("case", list(_order_cases()), ids=lambda case: f"{case[0]}, order {case[1]}")
def test_fitted_order_against_exact_and_reference_solutions(case):
    (system, method, y0, t1, _, reference, args), step_sizes = _order_cases()[case]
    if case[0] not in _REFERENCES:
        _REFERENCES[case[0]] = reference()
    order = case[1]
    errors = _errors(system, nh.Composition(method, order), y0, t1, step_sizes, _REFERENCES[case[0]], args)
    assert min(errors) >= 1e-13, errors  # above roundoff, so that the fit means something
    low, high = WITHIN[order]
    assert low <= fitted_order(step_sizes, errors) <= high, errors


def test_the_averaged_vector_field_method_composes():
    """DiscreteGradient(avf), symmetric like Gonzalez's: order 4 on Suslov's exact
    solution."""
    rho0 = SUSLOV.initial_state(omega1=1.0, omega2=0.5)
    step_sizes = (0.5, 0.25, 0.125)
    method = nh.Composition(nh.DiscreteGradient(nh.avf), 4)
    errors = _errors(SUSLOV.adapted, method, rho0, 10.0, step_sizes, SUSLOV.exact_solution(10.0, rho0), SUSLOV.args)
    assert 3.7 <= fitted_order(step_sizes, errors) <= 4.6, errors


def test_itoh_abe_is_symmetrised_with_its_adjoint_then_composed():
    r"""Itoh-Abe is first order and not symmetric; $\Phi_{h/2}\circ\Phi^*_{h/2}$ is
    symmetric and second order, and its composition of order 4 has order 4. Energy
    stays exact: the adjoint is a discrete-gradient method too."""
    itoh_abe = nh.DiscreteGradient(nh.itoh_abe)
    assert not itoh_abe.is_symmetric()
    # The quartic's reduced form (on a quadratic, separable H such as Suslov's,
    # Itoh-Abe is the midpoint gradient and symmetric).
    x0 = QUARTIC.initial_state(0.7)
    reference = _reference(QUARTIC.adapted, x0, 2.0)
    step_sizes = (0.1, 0.05, 0.025)
    plain = _errors(QUARTIC.adapted, itoh_abe, x0, 2.0, step_sizes, reference)
    assert fitted_order(step_sizes, plain) <= 1.2, plain
    symmetrised = _errors(QUARTIC.adapted, nh.Composition(itoh_abe, 2), x0, 2.0, step_sizes, reference)
    assert 1.9 <= fitted_order(step_sizes, symmetrised) <= 2.3, symmetrised
    composed = nh.Composition(itoh_abe, 4)
    runs = _runs(QUARTIC.adapted, composed, x0, 2.0, step_sizes)
    fourth = _errors(QUARTIC.adapted, composed, x0, 2.0, step_sizes, reference, runs=runs)
    assert 3.7 <= fitted_order(step_sizes, fourth) <= 4.6, fourth
    back, results = eqx.filter_jit(step_there_and_back)(QUARTIC.adapted, composed, x0, 0.2)
    assert all(result == diffrax.RESULTS.successful for result in results)
    np.testing.assert_allclose(back, x0, rtol=0, atol=1e-14)
    # Itoh-Abe's quadrature for nearly equal coordinates meets (discGradEn) to its
    # truncation error, a little above rounding: here over 80 steps at each step size.
    assert float(jnp.max(jnp.abs(runs.energy / runs.energy[:, :1] - 1))) <= 1e-12


def _roundoff_walk(substeps: int) -> float:
    """Four standard deviations of a random walk of `substeps` relative roundings of
    size eps: where an exactly conserved energy's error stays over that many substeps.
    (Which of its paths a run takes depends on how XLA compiled it: at t = 1000 below,
    1.0e-13 with the test suite's compilation, 7.0e-14 with the default.)"""
    return 4 * np.sqrt(substeps) * float(jnp.finfo(jnp.float64).eps)


def test_energy_and_constraint_to_roundoff_over_ten_thousand_steps():
    """Order 8 GONZALEZ-R on the gearbox (17 substeps per step, negative ones among
    them) and order 4 DiscreteGradient on the quartic's reduced form (5 substeps): the
    energy within a random walk of roundoff (3.7e-13 and 2.0e-13), the constraint to
    a few ulps."""
    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    solution = nh.integrate(GEARBOX.canonical, nh.Composition(nh.GonzalezR(), 8), y0, 0.1, 10_000, args=GEARBOX.args, save_every=100)
    assert relative_energy_error(solution) <= _roundoff_walk(17 * 10_000)
    assert float(jnp.max(jnp.abs(solution.constraint))) <= 2e-15
    x0 = QUARTIC.initial_state(0.9)
    reduced = nh.integrate(QUARTIC.adapted, nh.Composition(nh.DiscreteGradient(), 4), x0, 0.1, 10_000, save_every=100)
    assert relative_energy_error(reduced) <= _roundoff_walk(5 * 10_000)


@pytest.mark.parametrize("order", [4, 8])
def test_the_composed_step_is_symmetric(order):
    """h then -h returns the start, for the composition of GONZALEZ-R (whose predictor is
    carried across substeps of both signs)."""
    y0 = GEARBOX.random_initial_state(jax.random.key(2))
    method = nh.Composition(nh.GonzalezR(), order)
    back, results = eqx.filter_jit(step_there_and_back)(GEARBOX.canonical, method, y0, 0.3, GEARBOX.args)
    assert all(result == diffrax.RESULTS.successful for result in results)
    for a, b in zip(back, y0):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)


def test_iterations_per_substep_stay_close_to_the_base_methods():
    """The GONZALEZ-R predictor extrapolates with the substeps' signed sizes: iterations
    per substep of the order-6 composition at h = 0.4 are no more than those of the
    plain method at the largest substep, 0.8 h."""
    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    composed = nh.integrate(GEARBOX.canonical, nh.Composition(nh.GonzalezR(), 6), y0, 0.4, 100, args=GEARBOX.args, save_every=100)
    plain = nh.integrate(GEARBOX.canonical, nh.GonzalezR(), y0, 0.32, 125, args=GEARBOX.args, save_every=125)
    per_substep = np.asarray(composed.stats["substep_root_find_steps"]) / 100
    assert per_substep.shape == (9,)
    assert int(np.sum(composed.stats["substep_root_find_steps"])) == int(composed.stats["root_find_steps"])
    assert np.max(per_substep) <= float(plain.stats["root_find_steps"]) / 125 + 0.25, per_substep


def test_gradients_of_the_composed_flow_match_finite_differences():
    y0 = GEARBOX.random_initial_state(jax.random.key(3))
    method = nh.Composition(nh.GonzalezR(), 4)

    def loss(y0, args, dt):
        # Perturbations of y0 leave the constraint by 1e-6: GONZALEZ-R reads only the
        # momentum's component in the constraint's kernel, smoothly in (q, p).
        solution = nh.integrate(GEARBOX.canonical, method, y0, dt, 10, args=args, save_every=10, check_constraint=False)
        return jnp.sum(solution.ys[0][-1] ** 2) + jnp.sum(jnp.sin(solution.ys[1][-1]))

    args = GEARBOX.args  # the gearbox has no parameters: derivatives w.r.t. y0 and dt
    gradient = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(y0, args, jnp.asarray(0.1))
    value = jax.jit(loss)

    def central(shift):
        return (value(*shift(1e-6)) - value(*shift(-1e-6))) / 2e-6

    direction = jax.tree.map(lambda y: jax.random.normal(jax.random.key(4), y.shape), y0)
    along = central(lambda e: (jax.tree.map(lambda y, d: y + e * d, y0, direction), args, 0.1))
    expected = sum(jnp.vdot(g, d) for g, d in zip(gradient[0], direction))
    np.testing.assert_allclose(along, expected, rtol=1e-6)
    np.testing.assert_allclose(central(lambda e: (y0, args, 0.1 + e)), gradient[2], rtol=1e-6)


def test_per_trajectory_result_codes_name_the_failed_substep():
    method = nh.Composition(nh.GonzalezR(), 4)
    check_per_trajectory_result_codes(method)


def test_failed_substep_is_reported_and_named():
    """The fault of `check_per_trajectory_result_codes`, single: the error message and
    the statistics name a substep."""

    def hamiltonian(q, p, args):
        return 0.5 * (p @ p + q[0] ** 2 + q[1] ** 2) + jnp.sqrt(1.0 - q[2])

    system = nh.NonholonomicSystem(hamiltonian, lambda q, args: jnp.array([[1.0, jnp.sin(q[2]), 0.0]]))
    q = jnp.array([0.1, 0.2, 0.5])
    y0 = q, system.project_momentum(q, jnp.array([0.5, -0.5, 1.0]))
    method = nh.Composition(nh.GonzalezR(), 4)
    solution = nh.integrate(system, method, y0, 0.1, 40, throw=False)
    assert solution.result == nh.RESULTS.nonfinite_step
    assert 0 <= int(solution.stats["failed_substep"]) < 5
    with pytest.raises(RuntimeError, match=r"failed at step \d+ of 40 .*, substep [1-5] of 5: .*non-finite"):
        nh.integrate(system, method, y0, 0.1, 40)


def test_a_failed_composed_trajectory_has_nan_derivatives_and_spares_its_neighbour():
    """A skew-gradient system whose potential sqrt(1 - x2) pushes x2 past 1, where H is
    NaN: under vmap, the failing trajectory's code is nonfinite_step, its derivatives
    with respect to y0 and dt are NaN, and its neighbour's are finite."""

    def hamiltonian(x, args):
        return 0.5 * (x[0] ** 2 + x[1] ** 2 + x[3] ** 2) + jnp.sqrt(1.0 - x[2])

    def structure(x, args):
        return jnp.array([[0.0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1], [0, 0, -1, 0]], dtype=x.dtype)

    system = nh.SkewGradientSystem(hamiltonian, structure)
    method = nh.Composition(nh.DiscreteGradient(), 4)

    def loss(x0, dt):
        solution = nh.integrate(system, method, x0, dt, 40, throw=False)
        return solution.ys[0, 0] + solution.ys[-1, 0], solution.result

    starts = jnp.array([[0.3, 0.1, -3.0, -0.5], [0.3, 0.1, 0.5, 1.0]])
    (_, codes), _ = jax.vmap(lambda x: (loss(x, 0.1), None))(starts)
    assert (codes == nh.RESULTS.successful).tolist() == [True, False]
    assert bool((codes == nh.RESULTS.nonfinite_step)[1])
    gradient = jax.jit(jax.vmap(jax.grad(lambda x, dt: loss(x, dt)[0], argnums=(0, 1)), in_axes=(0, None)))(starts, 0.1)
    assert bool(jnp.all(jnp.isfinite(gradient[0][0]))) and bool(jnp.isfinite(gradient[1][0]))
    assert bool(jnp.all(jnp.isnan(gradient[0][1]))) and bool(jnp.isnan(gradient[1][1]))


def test_float32():
    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    check_float32(nh.Composition(nh.GonzalezR(), 4), GEARBOX, y0)


def test_chunked_runs_add_up_the_substep_statistics(tmp_path):
    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    method = nh.Composition(nh.GonzalezR(), 4)
    chunked = nh.run_chunked(GEARBOX.canonical, method, y0, 0.1, 40, args=GEARBOX.args, directory=tmp_path, chunk_steps=20, progress=False)
    whole = nh.integrate(GEARBOX.canonical, method, y0, 0.1, 40, args=GEARBOX.args)
    assert chunked.stats["substep_root_find_steps"].shape == (5,)
    assert int(jnp.sum(chunked.stats["substep_root_find_steps"])) == int(chunked.stats["root_find_steps"])
    assert int(chunked.stats["failed_substep"]) == -1
    np.testing.assert_allclose(chunked.ys[0][-1], whole.ys[0][-1], rtol=0, atol=1e-12)


def test_every_symmetric_method_composes():
    """Order 4 of each canonical method (the method's own where that is higher: the
    energy-preserving collocation of order 6 stays at 6), fitted on the gearbox against
    the index-1 reference at h = 0.2, 0.1, 0.05 (one compiled program per method)."""
    from ..helpers import METHODS

    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    reference = _reference(GEARBOX.canonical, y0, 2.0, GEARBOX.args)
    step_sizes = (0.2, 0.1, 0.05)
    for name, method in METHODS.items():
        if isinstance(method, (nh.DiscreteGradient, nh.GonzalezF)):
            continue  # composed on the reduced forms above; refused (see below)
        assert method.is_symmetric(), name
        composed = nh.Composition(method, 4)
        low, high = WITHIN[composed.order(None)]
        errors = _errors(GEARBOX.canonical, composed, y0, 2.0, step_sizes, reference, GEARBOX.args)
        assert low <= fitted_order(step_sizes, errors) <= high, (name, errors)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="not symmetric"):
        nh.Composition(diffrax.Tsit5())
    with pytest.raises(ValueError, match="A projected step is not symmetric"):
        nh.Composition(nh.Projection(diffrax.Dopri8()))
    with pytest.raises(ValueError, match=r"A composition is composed already: compose the method it composes"):
        nh.Composition(nh.Composition(nh.GonzalezR(), 4), 6)
    with pytest.raises(ValueError, match="one of \\[2, 4, 6, 8\\]"):
        nh.Composition(nh.GonzalezR(), 5)
    with pytest.raises(ValueError, match="one of"):
        nh.Composition(nh.GonzalezR(), True)
    with pytest.raises(ValueError, match="symmetric"):
        nh.Composition(nh.GonzalezR(), 4, coefficients=[0.5, 0.3, 0.2])
    with pytest.raises(ValueError, match="sum to 1"):
        nh.Composition(nh.GonzalezR(), 4, coefficients=[0.5, 0.5, 0.5])
    with pytest.raises(ValueError, match="finite"):
        nh.Composition(nh.GonzalezR(), 4, coefficients=[float("nan")])
    with pytest.raises(ValueError, match="finite"):
        nh.Composition(nh.GonzalezR(), 4, coefficients=[])
    with pytest.raises(ValueError, match="nonzero"):
        nh.Composition(nh.GonzalezR(), 2, coefficients=[0.0, 1.0, 0.0])
    with pytest.raises(ValueError, match="even int"):
        nh.Composition(nh.GonzalezR(), 3, coefficients=[1.0])

    class OneSided(nh.GonzalezR):
        def is_symmetric(self) -> bool:
            return False

    with pytest.raises(ValueError, match="OneSided is not symmetric"):
        nh.Composition(OneSided())
    # A SPARK tableau that is not self-adjoint (IIIC for the constraint force).
    from nhjax._solver._spark_tableau import lobatto_coefficients

    lobatto = lobatto_coefficients(2)
    tableau = nh.SPARKTableau(
        c=lobatto["c"], b=lobatto["b"], velocity=lobatto["IIIA"], force=lobatto["IIIB"],
        constraint_force=lobatto["IIIC"], constraint_weights=[[0.5, 0.5]], order=2,
    )
    with pytest.raises(ValueError, match="SPARK is not symmetric"):
        nh.Composition(nh.SPARK(tableau))


def test_the_recommended_schemes_and_their_sizes():
    method = nh.GonzalezR()
    assert [nh.Composition(method, order).stages for order in (2, 4, 6, 8)] == [1, 5, 9, 17]
    for scheme in nh.COMPOSITION_SCHEMES.values():
        gamma = np.asarray(scheme["coefficients"])
        assert gamma.tolist() == gamma[::-1].tolist()
        assert abs(np.sum(gamma) - 1) <= 1e-15
    assert nh.Composition(method, 6).order(None) == 6


def test_gonzalez_f_is_refused_because_composition_leaves_it_at_order_two():
    """GONZALEZ-F is symmetric, but off the constraint (which it keeps only to O(h^2)) its
    step is not close to the identity: composed anyway, it stays second order."""
    with pytest.raises(ValueError, match="Composition refuses GonzalezF: .*does not raise"):
        nh.Composition(nh.GonzalezF(), 4)

    class Unchecked(nh.GonzalezF):
        def composition_obstacle(self):
            return None

    y0 = GEARBOX.random_initial_state(jax.random.key(0))
    reference = _reference(GEARBOX.canonical, y0, 2.0, GEARBOX.args)
    step_sizes = (0.2, 0.1, 0.05)
    errors = _errors(GEARBOX.canonical, nh.Composition(Unchecked(), 4), y0, 2.0, step_sizes, reference, GEARBOX.args)
    assert fitted_order(step_sizes, errors) <= 2.3, errors
