"""Shared test helpers: order fitting and independent reference solutions."""

import jax
import jax.numpy as jnp
import numpy as np

import nhjax as nh


def fitted_order(step_sizes, errors) -> float:
    """Slope of log(error) against log(h), least squares."""
    slope, _ = np.polyfit(np.log(np.asarray(step_sizes)), np.log(np.asarray(errors)), 1)
    return float(slope)


def relative_energy_error(solution) -> float:
    return float(jnp.max(jnp.abs(solution.energy / solution.energy[0] - 1)))


def reference_final_state(system, y0, t1, args=None):
    """SPEC §4: the index-1 ODE (`NonholonomicSystem.vf`, the multiplier eliminated by
    autodiff) by adaptive Dopri8 at rtol = atol = 1e-13 (`nhjax.integrate_adaptive`)."""
    solution = nh.integrate_adaptive(system, y0, t1, args, rtol=1e-13, atol=1e-13)
    return jax.tree.map(lambda y: y[-1], solution.ys)


def step_there_and_back(system, method, y0, h, args=None):
    """One step of `method` with h, then one with -h (diffrax's step from t0 = h to
    t1 = 0), returning (the state after both, the diffrax result codes)."""
    state = method.init(system, 0.0, h, y0, args)
    y1, _, _, state, there = method.step(system, 0.0, h, y0, args, state, False)
    back, _, _, _, again = method.step(system, h, 0.0, y1, args, state, False)
    return back, (there, again)


def final_state_errors(system, method, y0, t1, step_sizes, reference, args=None, observe=None):
    """max |observe(y_N) - reference| after integrating to t1 with each step size;
    states may be tuples such as (q, p)."""
    observe = (lambda y: y) if observe is None else observe
    errors = []
    for h in step_sizes:
        n = round(t1 / h)
        solution = nh.integrate(system, method, y0, h, n, args=args, save_every=n)
        final = jax.tree.map(lambda y: y[-1], solution.ys)
        difference = jax.tree.map(lambda a, b: jnp.max(jnp.abs(a - b)), observe(final), reference)
        errors.append(float(max(jax.tree.leaves(difference))))
    return errors
