"""NonholonomicSystem: metric and multiplier by autodiff, the reduced system for a
Householder frame, and initial-state validation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh


SLEIGH = nh.examples.chaplygin_sleigh()
QUARTIC = nh.examples.chaotic_quartic()
DISK = nh.examples.rolling_disk()
GEARBOX = nh.examples.gearbox()


def _sleigh_state():
    return SLEIGH.from_adapted(jnp.array([0.3, -0.2, 0.7, 0.4, -0.6]))


def test_metric_from_autodiff_is_the_printed_sleigh_metric():
    q, _ = _sleigh_state()
    np.testing.assert_allclose(SLEIGH.canonical.metric(q, SLEIGH.args), SLEIGH.metric(q, SLEIGH.args), atol=1e-14)


@pytest.mark.parametrize("example, y0", [
    (SLEIGH, _sleigh_state()),
    (QUARTIC, QUARTIC.from_adapted(QUARTIC.initial_state(0.4))),
    (DISK, DISK.from_adapted(DISK.initial_state(theta=0.3))),
    (GEARBOX, GEARBOX.random_initial_state(jax.random.key(3))),
])
def test_index1_vector_field_keeps_the_constraint_and_the_energy(example, y0):
    """d/dt[A(q) v] = 0 and dH/dt = 0 along the index-1 field, by jvp."""
    system = example.canonical
    args = example.args
    tangent = system.vf(0.0, y0, args)
    _, constraint_rate = jax.jvp(lambda y: system.constraint_residual(y, args), (y0,), (tangent,))
    _, energy_rate = jax.jvp(lambda y: system.energy(y, args), (y0,), (tangent,))
    np.testing.assert_allclose(constraint_rate, 0.0, atol=1e-14)
    np.testing.assert_allclose(energy_rate, 0.0, atol=1e-14)
    np.testing.assert_allclose(system.constraint_residual(y0, args), 0.0, atol=1e-15)


def test_canonical_and_adapted_vector_fields_agree():
    """The sleigh's printed adapted equations and its canonical form (printed metric and
    constraint, multiplier by autodiff) describe the same motion: the (q, p) derivative
    of the map from adapted coordinates carries one field to the other."""
    x = jnp.array([0.3, -0.2, 0.7, 0.4, -0.6])
    adapted_rate = SLEIGH.adapted.vf(0.0, x, SLEIGH.args)
    _, mapped = jax.jvp(lambda x: SLEIGH.from_adapted(x), (x,), (adapted_rate,))
    canonical = SLEIGH.canonical.vf(0.0, SLEIGH.from_adapted(x), SLEIGH.args)
    for a, b in zip(mapped, canonical):
        np.testing.assert_allclose(a, b, atol=1e-14)


def test_project_momentum():
    q = jnp.array([0.1, 0.2, 0.9])
    p = jnp.array([0.5, -1.0, 0.3])
    system = SLEIGH.canonical
    projected = system.project_momentum(q, p, SLEIGH.args)
    np.testing.assert_allclose(system.constraint_residual((q, projected), SLEIGH.args), 0.0, atol=1e-15)
    np.testing.assert_allclose(system.project_momentum(q, projected, SLEIGH.args), projected, atol=1e-15)
    # The correction p - p' is a constraint force A^T mu.
    a = system.constraints(q, SLEIGH.args)
    mu, *_ = jnp.linalg.lstsq(a.T, p - projected)
    np.testing.assert_allclose(a.T @ mu, p - projected, atol=1e-15)


@pytest.mark.parametrize("derivative", ["autodiff", "central_difference"])
def test_reduced_gradient_and_structure(derivative):
    """(eq:Htgrad) with dX/dq equals autodiff of H(q, p(q, rho)); the structure is skew;
    Pi grad H reproduces the canonical motion (qdot = v, rhodot = d/dt X^T p); the
    matrix-free products Pi v (from products with the frame and with J and J^T) equal
    the formed Pi times v."""
    y = QUARTIC.from_adapted(QUARTIC.initial_state(0.4).at[7:].add(0.1))
    y = (y[0], QUARTIC.canonical.project_momentum(*y))
    system = QUARTIC.canonical
    signs = system.frame_signs(y[0], None)
    step = 1e-4 if derivative == "central_difference" else None
    reduced = nh.NonholonomicSystem.reduced(system, signs, derivative, step)
    from nhjax._reduced import ReducedSystem

    formulas = ReducedSystem(system, signs, derivative, step)
    zeta = system.to_reduced(y, None, signs)
    structure, gradient = formulas.structure_and_gradient(zeta, None)
    tolerance = 1e-13 if step is None else 10 * step**2
    np.testing.assert_allclose(gradient, jax.grad(reduced.hamiltonian)(zeta, None), atol=tolerance)
    np.testing.assert_array_equal(structure, -structure.T)
    np.testing.assert_allclose(structure, reduced.structure(zeta, None), atol=0)
    point = formulas.at(zeta, None)
    for v in jax.random.normal(jax.random.key(3), (3, zeta.shape[0]), dtype=zeta.dtype):
        np.testing.assert_allclose(point.structure_times(v), structure @ v, atol=1e-14)
    zeta_rate = structure @ gradient
    q_rate, p_rate = system.vf(0.0, y, None)
    _, canonical_zeta_rate = jax.jvp(lambda y: system.to_reduced(y, None, signs), (y,), ((q_rate, p_rate),))
    np.testing.assert_allclose(zeta_rate, canonical_zeta_rate, atol=tolerance)
    q, p = system.from_reduced(zeta, None, signs)
    np.testing.assert_allclose(p, y[1], atol=1e-15)


def test_functions_that_promote_a_float32_state_are_named_and_float64_args_are_not():
    """A NumPy float64 constant inside H or A promotes a float32 run's arrays, which a
    method's loop cannot carry: named before the run. A float64 parameter in args is
    converted to the state's dtype, as the run converts it, so a dissipation reading one
    is not taken for such a function."""
    q = jnp.array([0.1, 0.2, 0.3], dtype=jnp.float32)
    p = GEARBOX.canonical.project_momentum(q, jnp.array([0.4, 0.5, 0.6], dtype=jnp.float32))
    promoting_h = nh.NonholonomicSystem(lambda q, p, args: 0.5 * p @ p + np.float64(0.1) * jnp.sum(q), GEARBOX.canonical.constraints)
    promoting_a = nh.NonholonomicSystem(GEARBOX.canonical.hamiltonian, lambda q, args: GEARBOX.canonical.constraints(q, args).astype(jnp.float64))
    for system, name in [(promoting_h, r"hamiltonian\(q, p, args\)"), (promoting_a, r"constraints\(q, args\)")]:
        with pytest.raises(ValueError, match=name + " returned float64 for a state in float32"):
            nh.integrate(system, nh.SIDLA(), (q, p), 0.1, 3)
    skew = nh.SkewGradientSystem(lambda x, args: 0.5 * x @ x, lambda x, args: jnp.array([[0.0, 1.0], [-1.0, 0.0]], dtype=jnp.float64))
    with pytest.raises(ValueError, match=r"structure\(x, args\) returned float64 for a state in float32"):
        nh.integrate(skew, nh.DiscreteGradient(), jnp.ones(2, jnp.float32), 0.1, 3)
    damped = nh.NonholonomicSystem(
        GEARBOX.canonical.hamiltonian, GEARBOX.canonical.constraints, dissipation=lambda q, p, args: args["c"] * jnp.eye(3, dtype=q.dtype)
    )
    solution = nh.integrate(damped, nh.GonzalezR(), (q, p), 0.1, 3, args={"c": jnp.asarray(0.1, jnp.float64)})
    assert solution.result == nh.RESULTS.successful and solution.ys[1].dtype == jnp.float32


def test_bad_hamiltonians_and_states_are_named():
    constraints = GEARBOX.constraints
    q = jnp.array([0.1, 0.2, 0.3])
    p = GEARBOX.canonical.project_momentum(q, jnp.array([0.4, 0.5, 0.6]))
    quartic_in_p = nh.NonholonomicSystem(lambda q, p, args: 0.5 * p @ p + (p @ p) ** 2, constraints)
    linear_in_p = nh.NonholonomicSystem(lambda q, p, args: 0.5 * p @ p + p[2], constraints)
    indefinite = nh.NonholonomicSystem(lambda q, p, args: 0.5 * (p[0] ** 2 + p[1] ** 2 - p[2] ** 2), constraints)
    for system in [quartic_in_p, linear_in_p, indefinite]:
        with pytest.raises(Exception, match="not of mechanical type"):
            nh.integrate(system, nh.GonzalezF(), (q, p), 0.1, 3)
    with pytest.raises(Exception, match="violates the constraint"):
        nh.integrate(GEARBOX.canonical, nh.GonzalezF(), (q, p + 1e-6), 0.1, 3)
    rank_deficient = nh.NonholonomicSystem(GEARBOX.canonical.hamiltonian, lambda q, args: jnp.zeros((1, 3)) * q)
    with pytest.raises(Exception, match="full row rank"):
        nh.integrate(rank_deficient, nh.GonzalezF(), (q, p), 0.1, 3)
    with pytest.raises(ValueError, match="tuple \\(q, p\\)"):
        nh.integrate(GEARBOX.canonical, nh.GonzalezR(), jnp.concatenate([q, p]), 0.1, 3)
    with pytest.raises(ValueError, match="same shape"):
        nh.integrate(GEARBOX.canonical, nh.GonzalezR(), (q, p[:2]), 0.1, 3)
    with pytest.raises(ValueError, match="same dtype, got float32 and float64"):
        nh.integrate(GEARBOX.canonical, nh.GonzalezR(), (q.astype(jnp.float32), p), 0.1, 3)
    with pytest.raises(ValueError, match="1 <= k < 3"):
        nh.integrate(nh.NonholonomicSystem(GEARBOX.canonical.hamiltonian, lambda q, args: jnp.eye(3)), nh.GonzalezR(), (q, p), 0.1, 3)
    with pytest.raises(ValueError, match="central_difference"):
        nh.GonzalezR(derivative="finite")
    # What is not a function, where one goes, is named when the system is made.
    hamiltonian = GEARBOX.canonical.hamiltonian
    with pytest.raises(ValueError, match=r"NonholonomicSystem: hamiltonian must be a function hamiltonian\(q, p, args\)"):
        nh.NonholonomicSystem("0.5 * p @ p", constraints)
    with pytest.raises(ValueError, match=r"NonholonomicSystem: constraints must be a function .*, got None"):
        nh.NonholonomicSystem(hamiltonian, None)
    with pytest.raises(ValueError, match=r"NonholonomicSystem: force must be a function .* or None, got 0.0"):
        nh.NonholonomicSystem(hamiltonian, constraints, force=0.0)
    with pytest.raises(ValueError, match=r"NonholonomicSystem: dissipation must be a function .* or None"):
        nh.NonholonomicSystem(hamiltonian, constraints, dissipation=jnp.eye(3))
    with pytest.raises(ValueError, match=r"from_lagrangian: lagrangian must be a function lagrangian\(q, qdot, args\)"):
        nh.NonholonomicSystem.from_lagrangian(None, constraints)
    with pytest.raises(ValueError, match=r"SkewGradientSystem: structure must be a function structure\(x, args\)"):
        nh.SkewGradientSystem(lambda x, args: x @ x, jnp.zeros((2, 2)))
    # A slightly perturbed but projected momentum is fine.
    projected = GEARBOX.canonical.project_momentum(q, p + 1e-6)
    assert nh.integrate(GEARBOX.canonical, nh.GonzalezF(), (q, projected), 0.1, 3).result == nh.RESULTS.successful
