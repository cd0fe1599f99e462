"""A vmapped batch on every device JAX has (the CPU here; a GPU where one is present):
the batch stays on the device, keeps energy and constraint to roundoff, and equals the
trajectories run one at a time."""

import jax
import jax.numpy as jnp
import pytest

import nhjax as nh


GEARBOX = nh.examples.gearbox()
STEPS, SAVE_EVERY = 100, 20


def _run(y0):
    return nh.integrate(GEARBOX.canonical, nh.GonzalezR(), y0, 0.1, STEPS, save_every=SAVE_EVERY)


@pytest.mark.parametrize("device", jax.devices(), ids=lambda device: f"{device.platform}{device.id}")
def test_a_vmapped_batch_keeps_its_invariants_and_equals_the_single_runs(device):
    keys = jax.random.split(jax.random.key(5), 4)
    with jax.default_device(device):
        states = jax.device_put(jax.vmap(GEARBOX.random_initial_state)(keys), device)
        batch = jax.jit(jax.vmap(_run))(states)
        single = jax.jit(_run)
        singles = [single(jax.tree.map(lambda leaf, i=i: leaf[i], states)) for i in range(keys.shape[0])]
    assert batch.ys[0].devices() == {device}
    assert batch.ys[0].shape == (4, STEPS // SAVE_EVERY + 1, 3)
    assert bool(jnp.all(batch.result == nh.RESULTS.successful))
    energy = batch.energy
    assert float(jnp.max(jnp.abs(energy - energy[:, :1]) / jnp.abs(energy[:, :1]))) <= 1e-13
    # A(q) dH/dp at every saved state of every trajectory.
    residual = jax.vmap(jax.vmap(lambda q, p: GEARBOX.canonical.constraint_residual((q, p), None)))(*batch.ys)
    assert float(jnp.max(jnp.abs(residual))) <= 1e-14
    for i, alone in enumerate(singles):
        for in_batch, by_itself in zip(jax.tree.leaves(batch.ys), jax.tree.leaves(alone.ys)):
            # Not bitwise: the batched program fuses and rounds differently, and the
            # iteration counts may differ by an iteration where a step's stopping test
            # sits at the rounding.
            assert float(jnp.max(jnp.abs(in_batch[i] - by_itself))) <= 1e-13
