"""Both defining conditions (discGradEn), (discGradCons), and accuracy of value and
derivatives at nearly equal and equal points, on random polynomial and trigonometric H."""

import functools
import itertools

import equinox as eqx
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

import nhjax as nh


N = 3
DISCRETE_GRADIENTS = [nh.avf, nh.gonzalez, nh.itoh_abe]
SYMMETRIC = [nh.avf, nh.gonzalez]
settings.register_profile("nhjax", max_examples=25, deadline=None, derandomize=True)
settings.load_profile("nhjax")


MONOMIALS = np.array([e for e in itertools.product(range(5), repeat=N) if sum(e) <= 4])
TRIG_TERMS = 4


def polynomial(x, coefficients):
    """sum_k c_k x^e_k over all monomials of degree <= 4."""
    powers = jnp.stack([jnp.ones_like(x), x, x * x, x * x * x, x * x * x * x], axis=1)
    monomials = jnp.prod(powers[jnp.arange(N), MONOMIALS], axis=1)
    return coefficients @ monomials


def trigonometric(x, parameters):
    amplitudes, frequencies, phases = parameters
    return amplitudes @ jnp.sin(frequencies @ x + phases)


unit = st.floats(-1.0, 1.0, allow_nan=False, width=64)
vectors = st.lists(unit, min_size=N, max_size=N).map(np.array)


def arrays(shape):
    size = int(np.prod(shape))
    return st.lists(unit, min_size=size, max_size=size).map(lambda v: jnp.array(v).reshape(shape))


polynomials = st.tuples(
    arrays((len(MONOMIALS),)),
    st.lists(st.booleans(), min_size=len(MONOMIALS), max_size=len(MONOMIALS)),
).map(lambda cm: (polynomial, cm[0] * jnp.array(cm[1])))
trigonometrics = st.tuples(
    arrays((TRIG_TERMS,)), arrays((TRIG_TERMS, N)), arrays((TRIG_TERMS,))
).map(lambda p: (trigonometric, p))
functions = st.one_of(polynomials, trigonometrics)


@st.composite
def point_pairs(draw):
    """Points in [-0.5, 0.5]^N, at a random distance from 1 down to 1e-15."""
    x = 0.5 * draw(vectors)
    direction = draw(vectors)
    distance = 10.0 ** -draw(st.floats(0.0, 15.0))
    return jnp.array(x), jnp.array(x + distance * direction)


@functools.partial(jax.jit, static_argnums=(0, 1))
def evaluate(dg, f, x, x1, args):
    """Everything the tests compare, compiled once per (dg, f)."""
    return dict(
        value=dg(f, x, x1, args),
        reversed=dg(f, x1, x, args),
        change=f(x1, args) - f(x, args),
        scale=jnp.maximum(1.0, jnp.maximum(jnp.abs(f(x, args)), jnp.abs(f(x1, args)))),
        grad_x=jax.grad(f)(x, args),
        grad_mid=jax.grad(f)(0.5 * (x + x1), args),
        hessian=jax.hessian(f)(x, args),
        forward=jax.jacfwd(dg, argnums=2)(f, x, x1, args),
        reverse=jax.jacrev(dg, argnums=2)(f, x, x1, args),
        wrt_first=jax.jacrev(dg, argnums=1)(f, x, x1, args),
    )


@pytest.mark.parametrize("dg", DISCRETE_GRADIENTS, ids=lambda dg: dg.__name__)
@given(function=functions, points=point_pairs())
def test_energy_condition(dg, function, points):
    f, args = function
    x, x1 = points
    out = evaluate(dg, f, x, x1, args)
    defect = out["value"] @ (x1 - x) - out["change"]
    assert abs(float(defect)) <= 1e-13 * float(out["scale"])


@pytest.mark.parametrize("dg", DISCRETE_GRADIENTS, ids=lambda dg: dg.__name__)
@given(function=functions, x=vectors)
def test_consistency_condition(dg, function, x):
    f, args = function
    x = jnp.array(x)
    out = evaluate(dg, f, x, x, args)
    np.testing.assert_allclose(out["value"], out["grad_x"], rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("dg", SYMMETRIC, ids=lambda dg: dg.__name__)
@given(function=functions, points=point_pairs())
def test_symmetric_gradients_are_midpoint_gradient_to_second_order(dg, function, points):
    """|dg(x, x') - grad f((x + x')/2)| = O(|x' - x|^2), and dg(x, x') = dg(x', x), up
    to the rounding of Gonzalez's printed value, eps |f| / |x' - x|, which it keeps for
    nearly equal points so that (discGradEn) holds to rounding."""
    f, args = function
    x, x1 = points
    out = evaluate(dg, f, x, x1, args)
    distance = float(jnp.linalg.norm(x1 - x))
    error = float(jnp.max(jnp.abs(out["value"] - out["grad_mid"])))
    rounding = 16 * float(jnp.finfo(x.dtype).eps) * float(out["scale"]) / max(distance, 1e-300) if dg is nh.gonzalez else 0.0
    assert error <= 50 * distance**2 + 1e-13 * float(out["scale"]) + rounding
    np.testing.assert_allclose(out["value"], out["reversed"], rtol=1e-12, atol=1e-13)


def test_gonzalez_at_nearly_equal_points_keeps_the_energy_condition_and_accurate_derivatives():
    """At |x' - x| = 1e-10: the formula as printed has lost its derivative to
    cancellation and six digits of its value, while nh.gonzalez, whose difference
    f(x') - f(x) then comes from gradients along the segment, has the derivative Hess/2
    and the midpoint gradient to O(|x' - x|^2); (discGradEn) holds to the rounding of
    f(x') - f(x)."""
    f = lambda x, args: jnp.sin(x[0]) * x[1] ** 3 + jnp.cos(x[1] * x[2])  # noqa: E731
    x = jnp.array([0.3, -0.2, 0.4])
    x1 = x + 1e-10 * jnp.array([1.0, -0.5, 0.2])

    def printed(x1):
        d, m = x1 - x, 0.5 * (x + x1)
        g = jax.grad(f)(m, None)
        return g + (f(x1, None) - f(x, None) - g @ d) / (d @ d) * d

    midpoint = jax.grad(f)(0.5 * (x + x1), None)
    half_hessian = 0.5 * jax.hessian(f)(x, None)
    assert float(jnp.max(jnp.abs(jax.jacfwd(printed)(x1) - half_hessian))) > 1e-2
    assert float(jnp.max(jnp.abs(printed(x1) - midpoint))) > 1e-8
    derivative = jax.jacfwd(nh.gonzalez, argnums=2)(f, x, x1, None)
    np.testing.assert_allclose(derivative, half_hessian, rtol=0, atol=1e-8)
    value = nh.gonzalez(f, x, x1, None)
    np.testing.assert_allclose(value, midpoint, rtol=0, atol=1e-15)
    defect = value @ (x1 - x) - (f(x1, None) - f(x, None))
    rounding = float(jnp.finfo(x.dtype).eps) * (abs(float(f(x, None))) + abs(float(f(x1, None))))
    assert abs(float(defect)) <= 4 * rounding


def test_gonzalez_derivative_at_nearly_equal_points_where_the_values_difference_is_taken():
    """f = a sin(x0) + b sin(x0) + x1^2/2 with a = 1e3, b = 1 - 1e3: |f| is of size 1
    but its terms 1e3, so the values' difference is rounded far beyond eps |f| and the
    quadrature, which does not agree with it to that estimate, is not taken. The value
    is then the printed one, but the derivative must still be Hess/2 (that of the
    Taylor expansion), not the printed formula's, whose coefficient divides that
    rounding by |x' - x|^2 = 1e-18."""
    f = lambda x, args: args[0] * jnp.sin(x[0]) + args[1] * jnp.sin(x[0]) + 0.5 * x[1] ** 2  # noqa: E731
    args = (jnp.array(1e3), jnp.array(1.0 - 1e3))
    x = jnp.array([0.7, -0.3])
    x1 = x + 1e-9 * jnp.array([0.6, 0.8])
    derivative = jax.jit(jax.jacfwd(nh.gonzalez, argnums=2), static_argnums=0)(f, x, x1, args)
    np.testing.assert_allclose(derivative, 0.5 * jax.hessian(f)(x, args), rtol=0, atol=1e-8)


def test_gonzalez_resolves_motion_below_the_rounding_of_the_values():
    """f = 1 + |x|^2/2 moved by 1e-13: the values' difference is rounding alone (the
    motion changes f by 1e-26, eps |f| is 2e-16), yet nh.gonzalez is the gradient at the
    midpoint to its own rounding, as the exact discrete gradient of a quadratic is; the
    printed formula loses the gradient's component along the motion entirely."""
    f = lambda x, args: 1.0 + 0.5 * x @ x  # noqa: E731
    x = jnp.array([1e-13, -2e-13])
    x1 = x + jnp.array([1e-13, 2e-13])
    midpoint = 0.5 * (x + x1)
    np.testing.assert_allclose(nh.gonzalez(f, x, x1, None), midpoint, rtol=1e-12, atol=0)
    d = x1 - x
    printed = midpoint + (f(x1, None) - f(x, None) - midpoint @ d) / (d @ d) * d
    assert float(jnp.max(jnp.abs(printed - midpoint))) > 0.1 * float(jnp.max(jnp.abs(midpoint)))


def test_gonzalez_takes_the_values_where_the_quadrature_truncates():
    """An angle wound to 6283 (1000 turns), with f = -cos(theta) + theta/10: its
    increment of 0.15 counts as nearly equal against 1 + |theta| (the switch assumes
    derivatives of size 1 in those units), but the two-point rule misses the
    difference by 1e-8; the values' difference, exact to rounding, is taken."""
    f = lambda x, args: 0.5 * x[1] ** 2 - jnp.cos(x[0]) + 0.1 * x[0]  # noqa: E731
    x = jnp.array([0.3 + 2 * np.pi * 1000, 1e-4])
    x1 = x + jnp.array([0.15, 1e-3])
    change = f(x1, None) - f(x, None)
    defect = nh.gonzalez(f, x, x1, None) @ (x1 - x) - change
    rounding = float(jnp.finfo(x.dtype).eps) * (abs(float(f(x, None))) + abs(float(f(x1, None))))
    assert abs(float(defect)) <= 4 * rounding


@pytest.mark.parametrize("dg", [nh.gonzalez, nh.itoh_abe], ids=lambda dg: dg.__name__)
def test_energy_condition_beside_a_coordinate_far_from_the_origin(dg):
    """A position of 1e3 (a sleigh far from where it started) must not make the others'
    increments of 0.05 count as nearly equal: their local expansions would miss
    (discGradEn) by the truncation error, about 1e-10 here."""
    f = lambda x, args: jnp.sin(3 * x[1]) * jnp.exp(x[2]) + 1e-3 * x[0]  # noqa: E731
    x = jnp.array([1e3, 0.3, -0.2])
    x1 = x + jnp.array([0.05, 0.05, -0.05])
    change = f(x1, None) - f(x, None)
    defect = dg(f, x, x1, None) @ (x1 - x) - change
    assert abs(float(defect)) <= 1e-14


def _expected_jacobian(dg, hessian):
    """d dg(x, x')/dx' at x' = x: Hess/2 for the symmetric ones; for Itoh-Abe the strict
    lower triangle of the Hessian plus half its diagonal."""
    if dg is nh.itoh_abe:
        return jnp.tril(hessian, -1) + 0.5 * jnp.diag(jnp.diag(hessian))
    return 0.5 * hessian


@pytest.mark.parametrize("dg", DISCRETE_GRADIENTS, ids=lambda dg: dg.__name__)
@pytest.mark.parametrize("distance", [0.0, 1e-12, 1e-7])
@given(function=functions, x=vectors, direction=vectors)
def test_derivatives_at_and_near_equal_points(dg, distance, function, x, direction):
    f, args = function
    x = jnp.array(0.5 * x)
    x1 = x + distance * jnp.array(direction)
    out = evaluate(dg, f, x, x1, args)
    assert bool(jnp.all(jnp.isfinite(out["wrt_first"])))
    np.testing.assert_allclose(out["forward"], out["reverse"], rtol=1e-12, atol=1e-12)
    expected = _expected_jacobian(dg, out["hessian"])
    np.testing.assert_allclose(out["forward"], expected, rtol=0, atol=1e-9 + 1e3 * distance)


def test_avf_node_count_is_configurable_and_exact_for_polynomials():
    f = lambda x, args: x[0] ** 6 + x[0] * x[1] ** 2  # noqa: E731
    x, x1 = jnp.array([0.2, -0.7]), jnp.array([1.1, 0.4])
    exact_change = f(x1, None) - f(x, None)
    three_nodes = functools.partial(nh.avf, nodes=3)  # exact up to degree 6
    one_node = functools.partial(nh.avf, nodes=1)  # the midpoint gradient
    assert abs(float(three_nodes(f, x, x1, None) @ (x1 - x) - exact_change)) < 1e-14
    assert abs(float(one_node(f, x, x1, None) @ (x1 - x) - exact_change)) > 1e-3
    with pytest.raises(ValueError, match="node"):
        nh.avf(f, x, x1, None, nodes=0)


def _skew(x, args):
    del args
    return jnp.outer(x, x**2) - jnp.outer(x**2, x)


# Each function of two points: the discrete gradients (of a scalar function) and the
# structure approximations (of a skew-matrix function), with what each differences or
# averages and the shape of its value for points of shape (3,).
TWO_POINT_FUNCTIONS = [
    pytest.param(function, f, shape, id=function.__name__)
    for function, f, shape in (
        (nh.avf, lambda x, args: jnp.sum(x**4), (3,)),
        (nh.gonzalez, lambda x, args: jnp.sum(x**4), (3,)),
        (nh.itoh_abe, lambda x, args: jnp.sum(x**4), (3,)),
        (nh.midpoint_structure, _skew, (3, 3)),
        (nh.averaged_structure, _skew, (3, 3)),
    )
]


@pytest.mark.parametrize("function, f, shape", TWO_POINT_FUNCTIONS)
def test_points_of_other_shapes_or_integer_points_are_named(function, f, shape):
    """Two points of different shapes, a matrix, a scalar or integer coordinates: a
    ValueError naming the function and the problem, where JAX's own errors (broadcasting,
    unpacking, dtypes) did not say what was wrong, or (a structure approximation at
    integer points) none was raised."""
    name = function.__name__
    with pytest.raises(ValueError, match=rf"{name} takes two points of one shape, got shapes \(3,\) and \(4,\)"):
        function(f, jnp.ones(3), jnp.ones(4), None)
    for x, x_shape in ((jnp.ones((2, 3)), r"\(2, 3\)"), (jnp.array(1.0), r"\(\)")):
        with pytest.raises(ValueError, match=rf"{name}'s x must be a 1-D array, got shape {x_shape}"):
            function(f, x, x, None)
    with pytest.raises(ValueError, match=f"{name}'s x must be floating point, got dtype int"):
        function(f, jnp.arange(3), jnp.arange(3) + 1.0, None)
    with pytest.raises(ValueError, match=f"{name}'s x1 must be floating point, got dtype int"):
        function(f, jnp.arange(3) + 1.0, jnp.arange(3), None)
    assert function(f, jnp.ones(3), jnp.full(3, 2.0), None).shape == shape


class _Weighted(eqx.Module):
    """f(x, args) = a sum(w sin(x)) + x0 |x|^2, a callable whose array w is differentiated
    like an argument."""

    weights: jax.Array

    def __call__(self, x, args):
        return args["a"] * jnp.sum(self.weights * jnp.sin(x)) + x[0] * (x @ x)


def test_third_directional_derivative_rule_agrees_with_autodiff_of_the_difference():
    """The Taylor branch's third difference (`_third_directional_derivative`) is
    differentiated by its own rule, one reverse pass contracted with the tangents; forward
    and reverse autodiff of the same difference (`_third_difference`) are the other
    route. They must agree in the point, the direction, the arguments and the array f
    closes over, for a batch of tangents (`jax.jacfwd`), in reverse mode, and in second
    derivatives. A rule that dropped any of these tangents would miss by O(1)."""
    from nhjax._discrete_gradient import _third_difference, _third_directional_derivative

    x = jnp.array([0.4, -0.7, 1.1])
    direction = jnp.array([0.3, 0.5, -0.8])
    weights = jnp.array([1.5, -0.5, 2.0])

    def third(route, x, direction, a, weights):
        return route(_Weighted(weights), x, direction, dict(a=a))

    inputs = (x, direction, jnp.array(0.9), weights)
    argnums = (0, 1, 2, 3)
    by_rule = jax.jit(jax.jacfwd(functools.partial(third, _third_directional_derivative), argnums=argnums))(*inputs)
    by_autodiff = jax.jit(jax.jacfwd(functools.partial(third, _third_difference), argnums=argnums))(*inputs)
    reverse = jax.jit(jax.grad(functools.partial(third, _third_directional_derivative), argnums=argnums))(*inputs)
    for rule, autodiff, backward in zip(by_rule, by_autodiff, reverse):
        assert float(jnp.max(jnp.abs(autodiff))) > 0.1
        np.testing.assert_allclose(rule, autodiff, rtol=0, atol=1e-6)
        np.testing.assert_allclose(backward, autodiff, rtol=0, atol=1e-6)
    second = lambda route: jax.jit(jax.hessian(functools.partial(third, route)))(*inputs)  # noqa: E731
    np.testing.assert_allclose(second(_third_directional_derivative), second(_third_difference), rtol=0, atol=1e-4)
