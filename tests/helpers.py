"""Shared test helpers: order fitting and independent reference solutions."""

import diffrax
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


def quartic_reference(q0, p0, t1, n=3):
    """The chaotic quartic in canonical coordinates (M = I), written independently of
    nhjax's adapted form: qdot = v, vdot = -grad V + lambda a(q), with the multiplier
    eliminated from d/dt[a(q) . v] = 0, a = (1, 0_n, w). Dopri8 at rtol = atol = 1e-13.
    """

    def potential(q):
        w, z = q[1 : n + 1], q[n + 1 :]
        return 0.5 * (q @ q + z[0] ** 2 * z[1] ** 2 + jnp.sum(w**2 * z**2))

    def vector_field(t, state, args):
        q, v = state
        w = q[1 : n + 1]
        a = jnp.concatenate([jnp.ones(1), jnp.zeros(n), w])
        grad_v = jax.grad(potential)(q)
        adot_v = v[1 : n + 1] @ v[n + 1 :]
        multiplier = (a @ grad_v - adot_v) / (a @ a)
        return v, -grad_v + multiplier * a

    solution = diffrax.diffeqsolve(
        diffrax.ODETerm(vector_field),
        diffrax.Dopri8(),
        0.0,
        t1,
        0.01,
        (q0, p0),
        stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13),
        max_steps=100_000,
    )
    return jax.tree.map(lambda y: y[-1], solution.ys)


def reference_final_state(system, y0, t1, args=None):
    """SPEC §4: the index-1 ODE (`NonholonomicSystem.vf`, the multiplier eliminated by
    autodiff) by Dopri8 at rtol = atol = 1e-13."""
    solution = diffrax.diffeqsolve(
        system,
        diffrax.Dopri8(),
        0.0,
        t1,
        0.01,
        y0,
        args=args,
        stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13),
        max_steps=100_000,
    )
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
