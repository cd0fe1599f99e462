"""The contact oscillator (McLachlan & Perlmutter §5.2) in its canonical, adapted and
gauge-shifted forms: one motion, H_y a first integral, reversibility lost in the
gauge-shifted coordinates."""

import jax
import jax.numpy as jnp
import numpy as np

import nhjax as nh


OSCILLATOR = nh.examples.contact_oscillator()
TIGHT = dict(rtol=1e-13, atol=1e-13)


def _start():
    x0 = OSCILLATOR.initial_state()
    return OSCILLATOR.from_adapted(x0), x0


def test_initial_state_has_the_asked_energies_and_keeps_the_constraint():
    (q0, p0), adapted0 = _start()
    np.testing.assert_allclose(OSCILLATOR.canonical.constraint_residual((q0, p0), None), 0.0, atol=1e-16)
    assert abs(float(OSCILLATOR.canonical.energy((q0, p0), None)) - 1.5) < 1e-14
    assert abs(float(OSCILLATOR.y_energy(adapted0)) - 0.5) < 1e-15
    # The adapted form's H is the canonical H, and the gauge shift keeps it.
    assert abs(float(OSCILLATOR.adapted.energy(adapted0, None)) - 1.5) < 1e-14
    shifted0 = OSCILLATOR.to_gauge_shifted(adapted0)
    assert abs(float(OSCILLATOR.gauge_shifted.energy(shifted0, None)) - 1.5) < 1e-14
    np.testing.assert_allclose(OSCILLATOR.from_gauge_shifted(shifted0), adapted0, rtol=0, atol=1e-15)


def test_the_three_forms_are_one_motion_and_keep_y_energy():
    """The index-1 ODE in (q, p), the reduced equations and the gauge-shifted ones, each by
    Dopri8 at 1e-13, mapped to adapted coordinates: the same states at every save, and
    H_y = (y^2 + ydot^2)/2 constant along them."""
    (q0, p0), adapted0 = _start()
    times = jnp.linspace(0.0, 20.0, 11)
    canonical = nh.integrate_adaptive(OSCILLATOR.canonical, (q0, p0), 20.0, save_at=times, **TIGHT)
    adapted = nh.integrate_adaptive(OSCILLATOR.adapted, adapted0, 20.0, save_at=times, **TIGHT)
    shifted = nh.integrate_adaptive(
        OSCILLATOR.gauge_shifted, OSCILLATOR.to_gauge_shifted(adapted0), 20.0, save_at=times, **TIGHT
    )
    from_canonical = jax.vmap(OSCILLATOR.to_adapted)(*canonical.ys)
    from_shifted = jax.vmap(OSCILLATOR.from_gauge_shifted)(shifted.ys)
    np.testing.assert_allclose(from_canonical, adapted.ys, rtol=0, atol=1e-9)
    np.testing.assert_allclose(from_shifted, adapted.ys, rtol=0, atol=1e-9)
    y_energy = OSCILLATOR.y_energy(adapted.ys)
    np.testing.assert_allclose(y_energy, 0.5, rtol=0, atol=1e-10)
    assert float(jnp.max(jnp.abs(adapted.ys[:, 4] - adapted0[4]))) > 0.1  # the z motion is not trivial


def _reversed(state):
    return state.at[3:].multiply(-1)


def test_the_standard_reversibility_map_reverses_the_adapted_form_only():
    """R(q, rho) = (q, -rho): the flow of the adapted form satisfies R phi_t R phi_t = id;
    that of the gauge-shifted form, the same motion in other momenta, does not."""
    _, adapted0 = _start()
    for system, start, reversible in (
        (OSCILLATOR.adapted, adapted0, True),
        (OSCILLATOR.gauge_shifted, OSCILLATOR.to_gauge_shifted(adapted0), False),
    ):
        there = nh.integrate_adaptive(system, start, 3.0, **TIGHT).ys[-1]
        back = _reversed(nh.integrate_adaptive(system, _reversed(there), 3.0, **TIGHT).ys[-1])
        distance = float(jnp.max(jnp.abs(back - start)))
        assert (distance < 1e-9) if reversible else (distance > 1e-2), distance
        # The Hamiltonian is R-invariant exactly when the form is reversible.
        moved = abs(float(system.energy(_reversed(there), None) - system.energy(there, None)))
        assert (moved < 1e-14) if reversible else (moved > 1e-2), moved


def test_systems_built_alike_share_one_compilation(monkeypatch):
    """Each access of `.canonical` or `.gauge_shifted` builds a new system; equal
    parameters give equal systems, so a second run traces nothing: not the run, which
    `nhjax.integrate` keeps compiled, nor the potential for its shape check outside the
    compiled program, since a system's functions keep their traces
    (`nhjax._user_function`). Systems that differed would trace both again."""
    import nhjax.examples._contact_oscillator as module

    traces = []
    potential = module._potential

    def counted(q, epsilon):
        traces.append(None)
        return potential(q, epsilon)

    monkeypatch.setattr(module, "_potential", counted)
    (q0, p0), adapted0 = _start()
    for build, method, start in (
        (lambda: nh.examples.contact_oscillator().canonical, nh.SIDLA(), (q0, p0)),
        (lambda: nh.examples.contact_oscillator().gauge_shifted, nh.DiscreteGradient(),
         OSCILLATOR.to_gauge_shifted(adapted0)),
    ):
        assert build() == build()
        nh.integrate(build(), method, start, 0.1, 5)
        count = len(traces)
        nh.integrate(build(), method, start, 0.1, 5)
        assert len(traces) == count
