"""Systems from a Lagrangian (`NonholonomicSystem.from_lagrangian`): the Legendre
transform gives each example's Hamiltonian, every method gives the same trajectories
from either form, derivatives with respect to the Lagrangian's parameters agree with
finite differences, and a Lagrangian that is not of mechanical type is refused."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh

from .helpers import CANONICAL_METHODS, canonical_starts, METHODS


STARTS = canonical_starts()
EXAMPLES = {name: example for name, (example, _) in STARTS.items()}


@pytest.mark.parametrize("name", list(STARTS))
def test_the_legendre_transform_gives_the_examples_hamiltonian(name):
    example = EXAMPLES[name]
    given, derived = example.canonical, example.canonical_from_lagrangian
    n = STARTS[name][1][0].shape[0]
    keys = jax.random.split(jax.random.key(3), 2)
    qs, ps = (jax.random.normal(key, (20, n)) for key in keys)
    h_given = jax.jit(jax.vmap(given.hamiltonian, (0, 0, None)))(qs, ps, example.args)
    h_derived = jax.jit(jax.vmap(derived.hamiltonian, (0, 0, None)))(qs, ps, example.args)
    np.testing.assert_allclose(h_derived, h_given, rtol=1e-13, atol=1e-13)
    metric_given = jax.jit(jax.vmap(given.inverse_metric, (0, None)))(qs, example.args)
    metric_derived = jax.jit(jax.vmap(derived.inverse_metric, (0, None)))(qs, example.args)
    np.testing.assert_allclose(metric_derived, metric_given, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("name", list(STARTS) + ["Euler's disk"])
def test_the_legendre_transforms_derivatives_are_those_of_the_examples_hamiltonian(name):
    """The Legendre transform's derivatives come from first derivatives of L at the
    velocity (the envelope theorem); those of the hand-written H by autodiff through it:
    gradients in q, p and the parameters, second derivatives in (q, p) and the mixed
    ones in the parameters, at random states. The second derivatives of the Legendre
    transform differentiate its velocity M^-1 p by a rule of its own
    (`nhjax._lagrangian._legendre_velocity`)."""
    example = nh.examples.rolling_disk_3d() if name == "Euler's disk" else EXAMPLES[name]
    given, derived = example.canonical.hamiltonian, example.canonical_from_lagrangian.hamiltonian
    n = example.constraints(jnp.zeros(5), example.args).shape[1] if name == "Euler's disk" else STARTS[name][1][0].shape[0]
    keys = jax.random.split(jax.random.key(4), 2)
    qs, ps = (0.5 * jax.random.normal(key, (5, n)) for key in keys)
    args = jax.tree.map(jnp.asarray, example.args)

    parameters = (2,) if jax.tree.leaves(args) else ()  # the gearbox and the quartic have none

    def derivatives(hamiltonian):
        gradient = jax.grad(hamiltonian, (0, 1, *parameters))
        hessian = jax.jacfwd(jax.grad(hamiltonian, (0, 1)), (0, 1))
        mixed = jax.jacrev(jax.grad(hamiltonian, (0, 1)), parameters) if parameters else (lambda *_: ())
        return jax.jit(jax.vmap(lambda q, p: (gradient(q, p, args), hessian(q, p, args), mixed(q, p, args))))(qs, ps)

    expected = jax.tree.leaves(derivatives(given))
    for got, want in zip(jax.tree.leaves(derivatives(derived)), expected, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * (1 + float(jnp.max(jnp.abs(want)))))
    assert max(float(jnp.max(jnp.abs(leaf))) for leaf in expected) > 0.1  # not trivially zero


@pytest.mark.parametrize("name", list(STARTS) + ["Euler's disk", "Euler's disk, forced"])
def test_the_index_one_field_of_both_forms_agrees(name):
    """The index-1 field (the multiplier eliminated), which a system given by its
    Lagrangian computes from one formation of M (`LegendreHamiltonian.index_one_terms`)
    and one given by H by autodiff of H, and its Jacobian in (q, p), agree at random
    states; on Euler's disk also with a dissipation and a force, given to each form
    in its own variables."""
    if name.startswith("Euler's disk"):
        example = nh.examples.rolling_disk_3d()
        n = 5
    else:
        example = EXAMPLES[name]
        n = STARTS[name][1][0].shape[0]
    given, derived = example.canonical, example.canonical_from_lagrangian
    if name.endswith("forced"):
        damping = lambda q: jnp.diag(0.1 + 0.05 * jnp.cos(q))  # noqa: E731
        push = lambda t, q: jnp.sin(t + jnp.arange(n) + q)  # noqa: E731
        given = nh.NonholonomicSystem(given.hamiltonian, example.constraints, lambda q, p, args: damping(q),
                                      lambda t, q, p, args: push(t, q))
        derived = nh.NonholonomicSystem.from_lagrangian(
            example.lagrangian, example.constraints, dissipation=lambda q, qdot, args: damping(q),
            force=lambda t, q, qdot, args: push(t, q))
    keys = jax.random.split(jax.random.key(5), 2)
    qs, ps = (0.5 * jax.random.normal(key, (5, n)) for key in keys)

    def field_and_jacobian(system):
        field = lambda y: jnp.concatenate(system.vf(0.7, y, example.args))  # noqa: E731
        return jax.jit(jax.vmap(lambda q, p: (field((q, p)), jax.jacfwd(field)((q, p)))))(qs, ps)

    expected = jax.tree.leaves(field_and_jacobian(given))
    for got, want in zip(jax.tree.leaves(field_and_jacobian(derived)), expected, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11 * (1 + float(jnp.max(jnp.abs(want)))))
    assert min(float(jnp.max(jnp.abs(leaf))) for leaf in expected) > 0.1  # not trivially zero


@pytest.mark.parametrize("name", ["sleigh, q-dependent M", "Euler's disk"])
def test_h_at_one_position_is_the_same_from_either_form(name):
    """`at_position`, which from a Lagrangian forms M(q) and its inverse once and from H
    differentiates H: the velocity, dH/dq, K and M v agree between the two forms (and
    with the system's own velocity), M v inverts the velocity, and derivatives through
    them in q and p agree too."""
    if name == "Euler's disk":
        example = nh.examples.rolling_disk_3d()
        n = 5
    else:
        example = EXAMPLES[name]
        n = STARTS[name][1][0].shape[0]
    keys = jax.random.split(jax.random.key(6), 2)
    qs, ps = (0.5 * jax.random.normal(key, (4, n)) for key in keys)

    def evaluations(system):
        def at(q, p):
            point = system.at_position(q, example.args)
            v = point.velocity(p)
            return dict(
                velocity=v,
                position_gradient=point.position_gradient(p),
                inverse_metric=point.inverse_metric(),
                round_trip=point.momentum(v),
                system_velocity=system.velocity(q, p, example.args),
            )

        derivative = jax.jacfwd(lambda q, p: at(q, p)["position_gradient"], (0, 1))
        return jax.jit(jax.vmap(lambda q, p: (at(q, p), derivative(q, p))))(qs, ps)

    given, derived = evaluations(example.canonical), evaluations(example.canonical_from_lagrangian)
    for got, want in zip(jax.tree.leaves(derived), jax.tree.leaves(given), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11 * (1 + float(jnp.max(jnp.abs(want)))))
    for values, _ in (given, derived):
        np.testing.assert_allclose(values["round_trip"], ps, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(values["velocity"], values["system_velocity"], rtol=1e-12, atol=1e-12)
    assert float(jnp.max(jnp.abs(given[0]["position_gradient"]))) > 1e-3  # the metric depends on q


def test_the_momentum_of_a_velocity_is_the_lagrangians_derivative():
    """p = M(q) qdot against dL/dqdot by autodiff of the Lagrangian itself, on the
    sleigh (q-dependent M); for a velocity on the constraint, p is on it too."""
    sleigh = EXAMPLES["sleigh, q-dependent M"]
    system = sleigh.canonical_from_lagrangian
    q = jnp.array([0.3, -1.0, 0.7])
    qdot = system.frame(q, sleigh.args, system.frame_signs(q, sleigh.args)) @ jnp.array([0.4, -0.9])
    p = system.momentum_from_velocity(q, qdot, sleigh.args)
    lagrangian = system.hamiltonian.lagrangian
    np.testing.assert_allclose(p, jax.grad(lagrangian, argnums=1)(q, qdot, sleigh.args), rtol=1e-14, atol=1e-14)
    assert float(jnp.max(jnp.abs(system.constraint_residual((q, p), sleigh.args)))) <= 1e-14
    np.testing.assert_allclose(system.velocity(q, p, sleigh.args), qdot, atol=1e-14)


def test_a_lagrangian_free_of_q_and_of_parameters_has_the_free_bodys_gradient():
    """L = 1/2 qdot^T diag(m) qdot with the masses as numbers depends on neither q nor
    args, so the Legendre transform's derivative along q and args is a symbolic zero:
    the gradient of H = 1/2 p^T diag(m)^-1 p is (0, p / m), by reverse and forward
    mode, and the system's velocity is p / m."""
    masses = np.array([2.0, 3.0, 0.5])

    def lagrangian(q, qdot, args):
        del q, args
        return 0.5 * jnp.sum(masses * qdot**2)

    system = nh.NonholonomicSystem.from_lagrangian(lagrangian, lambda q, args: jnp.array([[1.0, 0.0, -1.0]]))
    q, p = jnp.array([0.3, -0.2, 1.1]), jnp.array([0.5, -1.5, 2.0])
    reverse = jax.grad(system.hamiltonian, argnums=(0, 1))(q, p, None)
    forward = jax.jacfwd(system.hamiltonian, argnums=(0, 1))(q, p, None)
    for grad_q, grad_p in (reverse, forward, (None, jax.grad(system.hamiltonian, argnums=1)(q, p, None))):
        if grad_q is not None:
            np.testing.assert_array_equal(grad_q, np.zeros(3))
        np.testing.assert_allclose(grad_p, p / masses, rtol=1e-15)
    np.testing.assert_allclose(system.velocity(q, p, None), p / masses, rtol=1e-15)


def _final_state(system, method, y0, args, n_steps=50):
    solution = nh.integrate(system, method, y0, 0.1, n_steps, args=args, save_every=n_steps)
    assert solution.result == nh.RESULTS.successful
    return jax.tree.map(lambda y: y[-1], solution.ys)


CASES = [(method, "sleigh, q-dependent M") for method in CANONICAL_METHODS] + [
    ("gonzalez-r", name) for name in STARTS if name != "sleigh, q-dependent M"
]


@pytest.mark.parametrize("method, name", CASES)
def test_both_forms_give_the_same_trajectory(method, name):
    """Every method on the sleigh, whose metric depends on q, and GONZALEZ-R on the
    others: 50 steps from either form agree to rounding (the forms compute M^-1 by
    different routes)."""
    example, y0 = STARTS[name]
    given = _final_state(example.canonical, METHODS[method], y0, example.args)
    derived = _final_state(example.canonical_from_lagrangian, METHODS[method], y0, example.args)
    for a, b in zip(given, derived):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-11)


def test_derivatives_with_respect_to_the_lagrangians_parameters():
    """d x_1(t = 5) / d J on the Chaplygin sleigh with SI-DLA, from a start given by
    positions and velocities (its momentum M qdot depends on J too): from the
    Lagrangian form, equal to the Hamiltonian form's and to a central difference.
    Forward mode, the mode for one parameter (reverse mode through every method:
    test_integrate_gradients.py)."""
    sleigh, (q0, _) = STARTS["sleigh, q-dependent M"]
    qdot0 = sleigh.frame(q0, sleigh.args) @ jnp.array([0.3, -0.6])  # on the constraint
    method = nh.SIDLA()

    def final_x(system, inertia):
        args = dict(sleigh.args, J=inertia)
        y0 = (q0, system.momentum_from_velocity(q0, qdot0, args))
        solution = nh.integrate(system, method, y0, 0.1, 50, args=args, save_every=50, adjoint=diffrax.ForwardMode())
        return solution.ys[0][-1, 0]

    inertia = jnp.asarray(sleigh.args["J"], dtype=jnp.float64)
    derived = jax.jit(jax.jacfwd(lambda j: final_x(sleigh.canonical_from_lagrangian, j)))(inertia)
    given = jax.jit(jax.jacfwd(lambda j: final_x(sleigh.canonical, j)))(inertia)
    step = 1e-5
    difference = (final_x(sleigh.canonical_from_lagrangian, inertia + step)
                  - final_x(sleigh.canonical_from_lagrangian, inertia - step)) / (2 * step)
    assert abs(float(derived)) > 1e-3  # the parameter matters
    np.testing.assert_allclose(derived, given, rtol=1e-10)
    np.testing.assert_allclose(derived, difference, rtol=1e-7)


def _constraints(q, args):
    one = jnp.ones_like(q[0])
    return jnp.stack([-q[1], 0.0 * one, one])[None, :]


NOT_MECHANICAL = {
    "quartic in qdot": lambda q, qdot, args: 0.5 * qdot @ qdot + 0.1 * (qdot @ qdot) ** 2 - 0.5 * q @ q,
    "linear in qdot": lambda q, qdot, args: 0.5 * qdot @ qdot + q[0] * qdot[1] - 0.5 * q @ q,
    "M not positive definite": lambda q, qdot, args: 0.5 * (qdot[0] ** 2 - qdot[1] ** 2 + qdot[2] ** 2) - 0.5 * q @ q,
}


@pytest.mark.parametrize("name", list(NOT_MECHANICAL))
def test_a_lagrangian_not_of_mechanical_type_is_refused(name):
    system = nh.NonholonomicSystem.from_lagrangian(NOT_MECHANICAL[name], _constraints)
    # On the constraint v_z = y v_x for M = I and for M = diag(1, -1, 1).
    y0 = (jnp.array([0.3, -0.2, 0.1]), jnp.array([0.5, 0.4, -0.1]))
    with pytest.raises(RuntimeError, match="Lagrangian .* is not of mechanical type"):
        nh.integrate(system, nh.SIDLA(), y0, 0.1, 5)
    solution = nh.integrate(system, nh.SIDLA(), y0, 0.1, 5, throw=False)
    assert solution.result == nh.RESULTS.lagrangian_not_mechanical


def test_a_mechanical_lagrangian_of_the_same_shape_is_accepted():
    """The control for the refusals: the same particle with a mechanical Lagrangian."""
    system = nh.NonholonomicSystem.from_lagrangian(lambda q, qdot, args: 0.5 * qdot @ qdot - 0.5 * q @ q, _constraints)
    q = jnp.array([0.3, -0.2, 0.1])
    y0 = (q, system.project_momentum(q, jnp.array([0.5, 0.4, -0.1])))
    solution = nh.integrate(system, nh.GonzalezR(), y0, 0.1, 100)
    assert solution.result == nh.RESULTS.successful
    assert float(jnp.max(jnp.abs(solution.energy / solution.energy[0] - 1))) <= 1e-13


@pytest.mark.parametrize("method", ["sidla", "gonzalez-r"])
def test_a_lagrangian_that_turns_non_mechanical_along_the_run_is_caught_there(method):
    """5 q0^2 |qdot|^4 vanishes at the start (q0 = 0), so the initial check passes; the
    run's first step moves q0, and the step's end fails the check, where before the run
    went on with the Hamiltonian of another system and reported success."""
    lagrangian = lambda q, qdot, args: 0.5 * qdot @ qdot + 5 * q[0] ** 2 * jnp.sum(qdot**4) - 0.5 * q @ q  # noqa: E731
    system = nh.NonholonomicSystem.from_lagrangian(lagrangian, _constraints)
    q = jnp.array([0.0, -0.2, 0.1])
    y0 = (q, system.project_momentum(q, jnp.array([0.5, 0.4, -0.1])))
    solution = nh.integrate(system, METHODS[method], y0, 0.1, 20, throw=False)
    assert solution.result == nh.RESULTS.lagrangian_not_mechanical
    assert bool(jnp.all(jnp.isfinite(solution.ys[0][0])))  # the start was accepted
    assert not bool(jnp.all(jnp.isfinite(solution.ys[0][-1])))


def test_momenta_of_a_singular_mass_matrix_are_refused_naming_it():
    """M = diag(1, 0, 1): no momentum describes a velocity; momentum_from_velocity says
    so, where it gave NaN and the run then blamed the initial state."""
    system = nh.NonholonomicSystem.from_lagrangian(
        lambda q, qdot, args: 0.5 * (qdot[0] ** 2 + qdot[2] ** 2) - 0.5 * q @ q, _constraints
    )
    with pytest.raises(ValueError, match="mass matrix .* not symmetric positive definite"):
        system.momentum_from_velocity(jnp.array([0.3, -0.2, 0.1]), jnp.array([0.5, 0.4, -0.1]), None)
    healthy = nh.NonholonomicSystem.from_lagrangian(lambda q, qdot, args: 0.5 * qdot @ qdot - 0.5 * q @ q, _constraints)
    p = healthy.momentum_from_velocity(jnp.array([0.3, -0.2, 0.1]), jnp.array([0.5, 0.4, -0.1]), None)
    np.testing.assert_allclose(p, [0.5, 0.4, -0.1], rtol=1e-15)


def test_a_lagrangian_that_is_not_a_scalar_is_refused_naming_it():
    system = nh.NonholonomicSystem.from_lagrangian(lambda q, qdot, args: jnp.stack([qdot @ qdot, q @ q]), _constraints)
    y0 = (jnp.array([0.3, -0.2, 0.1]), jnp.array([0.5, 0.4, -0.1]))
    with pytest.raises(ValueError, match=r"lagrangian\(q, qdot, args\) must return a scalar, got \(2,\)"):
        nh.integrate(system, nh.SIDLA(), y0, 0.1, 5)
