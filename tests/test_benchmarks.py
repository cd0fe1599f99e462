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
