"""The benchmark suite's NumPy peers must compute what nhjax computes, or its speed
ratios compare different things: the NumPy + fsolve GONZALEZ-R against nhjax's
GONZALEZ-R with central-difference frame derivatives (the same method, implemented
independently), and the NumPy index-1 vector field against nhjax's (autodiff)."""

import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh


sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "benchmarks"))
import peers  # noqa: E402


def _cases():
    gearbox = nh.examples.gearbox()
    quartic = nh.examples.chaotic_quartic(3)
    return [
        ("gearbox", peers.GEARBOX, gearbox.canonical, gearbox.random_initial_state(jax.random.key(0))),
        ("quartic", peers.QUARTIC3, quartic.canonical, quartic.from_adapted(quartic.initial_state(0.7))),
    ]


@pytest.mark.parametrize(("name", "problem", "system", "y0"), _cases(), ids=lambda c: c if isinstance(c, str) else "")
def test_numpy_gonzalez_r_is_nhjax_gonzalez_r(name, problem, system, y0):
    steps = 20
    method = nh.GonzalezR(derivative="central_difference")
    ours = nh.integrate(system, method, y0, 0.1, steps)
    theirs = peers.gonzalez_r_numpy(problem, np.asarray(y0[0]), np.asarray(y0[1]), 0.1, steps)
    assert np.max(np.abs(theirs["q"] - np.asarray(ours.ys[0]))) <= 1e-12
    assert np.max(np.abs(theirs["p"] - np.asarray(ours.ys[1]))) <= 1e-12
    # Not a trivially stationary state: the trajectory moves.
    assert np.max(np.abs(theirs["q"][-1] - theirs["q"][0])) > 0.1


@pytest.mark.parametrize(("name", "problem", "system", "y0"), _cases(), ids=lambda c: c if isinstance(c, str) else "")
def test_numpy_index1_vector_field_is_nhjax_vector_field(name, problem, system, y0):
    q, p = (np.asarray(leaf) for leaf in y0)
    theirs = peers.index1_vector_field(problem)(0.0, np.concatenate([q, p]))
    ours = jnp.concatenate(system.vf(0.0, y0, None))
    assert np.max(np.abs(theirs - np.asarray(ours))) <= 1e-13 * (1 + np.max(np.abs(theirs)))


import _profile  # noqa: E402


def test_hlo_counts_count_operations_outside_fusions():
    x = jnp.linspace(0.0, 1.0, 64)
    elementwise = _profile.hlo_counts(jax.jit(lambda v: jnp.sin(3.0 * jnp.cos(v)) + 1.0).lower(x).compile())
    # One fused kernel of four or more instructions.
    assert elementwise["operations"] == 1
    assert elementwise["hlo_instructions"] >= 4
    matrix = jnp.outer(x, x)
    with_products = _profile.hlo_counts(jax.jit(lambda v: jnp.sin(matrix @ jnp.cos(matrix @ v))).lower(x).compile())
    assert with_products["operations"] >= 3


def test_distinct_fusions_count_a_repeated_computation_once():
    """Two fusions of the same computation on different inputs are one kernel; with
    different functions they are two."""
    x = jnp.linspace(0.0, 1.0, 64).reshape(8, 8)
    y = x[::-1]
    repeated = _profile.hlo_counts(jax.jit(lambda a, b: jnp.sin(jnp.cos(a)) @ jnp.sin(jnp.cos(b))).lower(x, y).compile())
    different = _profile.hlo_counts(jax.jit(lambda a, b: jnp.sin(jnp.cos(a)) @ jnp.tanh(jnp.exp(b))).lower(x, y).compile())
    assert repeated["operations"] == different["operations"]
    assert different["distinct_fusions"] == repeated["distinct_fusions"] + 1


def test_derivative_contexts_attribute_every_instruction_of_a_reverse_program():
    """A reverse-mode program of the replay's shape, a checkpointed scan whose step
    forms its Jacobian's rows by a vmapped pullback: every instruction is counted once,
    each context holds some, and without reverse mode around the scan none is in a
    backward sweep."""

    def step(x, _):
        value, pullback = jax.vjp(lambda v: jnp.sin(v) * jnp.cos(v[::-1]), x)
        rows = jax.vmap(pullback)(jnp.eye(x.shape[0]))[0]
        return value + jnp.tanh(rows @ x), None

    def loss(x):
        return jnp.sum(jax.lax.scan(jax.checkpoint(step), x, None, length=5)[0] ** 2)

    x = jnp.linspace(0.1, 0.9, 6)
    compiled = jax.jit(jax.grad(loss)).lower(x).compile()
    contexts = _profile.derivative_contexts(compiled)
    assert sum(contexts.values()) == _profile.hlo_counts(compiled)["hlo_instructions"]
    assert all(count > 0 for count in contexts.values()), contexts
    # Without reverse mode around it the scan has no backward sweep: only the step's
    # own rows.
    forward_only = _profile.derivative_contexts(jax.jit(loss).lower(x).compile())
    assert forward_only["transposed"] == forward_only["rematerialised"] == 0
    assert forward_only["vmapped_transposes"] > 0 and forward_only["forward"] > 0 and forward_only["no_work"] > 0


def _profiled_systems():
    sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "benchmarks"))
    import scaling

    synthetic, _, synthetic_start, _ = scaling.FAMILIES["synthetic"][0](8)
    trailers = nh.examples.tractor_trailers(2)
    return [
        ("synthetic, n = 8 (M = I)", synthetic, synthetic_start, None),
        ("tractor with 2 trailers (M(q))", trailers.canonical, trailers.initial_state(), trailers.args),
    ]


@pytest.mark.parametrize(("name", "system", "y0", "args"), _profiled_systems(), ids=lambda c: c if isinstance(c, str) else "")
def test_gonzalez_r_profile_pieces_make_its_residual(name, system, y0, args):
    """The profile times GONZALEZ-R's own pieces: the field's structure applied to the
    corrected gradient of `correction` gives the method's residual, at a point that is
    not a root."""
    method = nh.GonzalezR()
    h = 0.05
    data = method.setup(system, 0.0, h, y0, args, method.initial_carry(system, y0, args))[1]
    first_root = _profile.gonzalez_r_pieces(system, method, y0, h, args)[1]["residual"]
    u = 1.5 * first_root + 1e-3
    functions, arguments = _profile.gonzalez_r_pieces(system, method, y0, h, args, unknowns=u)
    zeta1 = data.zeta + data.scale * u
    assert np.array_equal(arguments["correction"], zeta1)
    corrected = functions["correction"](zeta1)
    structure = data.reduced.at(0.5 * (data.zeta + zeta1), args)
    by_pieces = u - h * structure.structure_times(corrected) / data.scale
    residual = method.residual(u, data)
    assert np.max(np.abs(residual)) > 1e-4
    assert np.max(np.abs(by_pieces - residual)) <= 1e-13 * np.max(np.abs(residual))
    # The correction's derivative at nearly equal points is finite (its Taylor form).
    assert np.all(np.isfinite(functions["taylor_derivative"](arguments["taylor_derivative"])))
