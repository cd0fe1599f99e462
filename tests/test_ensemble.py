import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax as nh


GEARBOX = nh.examples.gearbox()
METHOD = nh.GonzalezF()


def _states(count, seed=1):
    return jax.vmap(GEARBOX.random_initial_state)(jax.random.split(jax.random.key(seed), count))


def _max_difference(a, b):
    return max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_one_device_equals_vmap_of_integrate():
    """The same saves to 1e-13 and the same iterations up to one per trajectory: the
    sharded program is compiled apart from the vmapped one, and an iteration that ends
    at the rounding floor can take one more in one of them (at XLA's default
    optimisation these took 239, 241 and 275 against 239, 240 and 275)."""
    states = _states(3)
    sharded = nh.integrate_ensemble(GEARBOX.canonical, METHOD, states, 0.1, 40, save_every=10)
    reference = jax.vmap(lambda y: nh.integrate(GEARBOX.canonical, METHOD, y, 0.1, 40, save_every=10))(states)
    assert sharded.ys[0].shape == (3, 5, 3)
    assert _max_difference(sharded.ys, reference.ys) <= 1e-13
    assert _max_difference(sharded.energy, reference.energy) <= 1e-13
    assert jnp.all(jnp.abs(sharded.stats["root_find_steps"] - reference.stats["root_find_steps"]) <= 1)
    assert jnp.all(reference.stats["root_find_steps"] >= 40)


def test_compositions_run_as_ensembles_with_their_substep_statistics():
    """A composition's per-substep iterations come out of the sharded run as out of
    vmap's, up to one per substep, for the reason `test_one_device_equals_vmap_of_integrate`
    gives (here 87 against 86 iterations of one substep over 20 steps, the states 2e-15
    apart)."""
    quartic = nh.examples.chaotic_quartic(3)
    states = quartic.random_initial_states(jax.random.key(2), 3)
    method = nh.Composition(nh.DiscreteGradient(), 4)
    sharded = nh.integrate_ensemble(quartic.adapted, method, states, 0.1, 20, save_every=10)
    reference = jax.vmap(lambda x: nh.integrate(quartic.adapted, method, x, 0.1, 20, save_every=10))(states)
    assert _max_difference(sharded.ys, reference.ys) <= 1e-13
    assert sharded.stats["substep_root_find_steps"].shape == (3, 5)
    difference = sharded.stats["substep_root_find_steps"] - reference.stats["substep_root_find_steps"]
    assert jnp.all(jnp.abs(difference) <= 1)
    assert jnp.all(reference.stats["substep_root_find_steps"] >= 80)
    assert jnp.all(sharded.stats["failed_substep"] == -1)


def test_parameters_reach_every_trajectory():
    """`args` with array and float leaves (the sleigh's J, a, m) is shared by the batch:
    changing J changes every trajectory as it changes `integrate`'s."""
    sleigh = nh.examples.chaplygin_sleigh()

    def run(args):
        states = jax.vmap(lambda rho2: sleigh.from_adapted(sleigh.initial_state(rho2=rho2), args))(
            jnp.array([-0.6, -0.3])
        )
        sharded = nh.integrate_ensemble(sleigh.canonical, METHOD, states, 0.1, 20, args=args)
        reference = jax.vmap(lambda y: nh.integrate(sleigh.canonical, METHOD, y, 0.1, 20, args=args))(states)
        return sharded, reference

    sharded, reference = run(dict(sleigh.args, J=jnp.asarray(6.0)))
    default, _ = run(sleigh.args)
    assert _max_difference(sharded.ys, reference.ys) <= 1e-13
    assert _max_difference(sharded.ys, default.ys) > 1e-5


def test_each_trajectory_has_its_own_result():
    q, p = _states(3)
    q = q.at[1, 0].set(jnp.nan)
    solution = nh.integrate_ensemble(GEARBOX.canonical, METHOD, (q, p), 0.1, 20, throw=False)
    codes = [nh.RESULTS[jax.tree.map(lambda c: c[i], solution.result)] for i in range(3)]
    assert codes[1] == nh.RESULTS[nh.RESULTS.nonfinite_initial_state]
    assert codes[0] == codes[2] == nh.RESULTS[nh.RESULTS.successful]
    assert jnp.all(jnp.isfinite(solution.ys[0][jnp.array([0, 2])]))
    with pytest.raises(RuntimeError, match=r"1 of 3 trajectories failed; trajectory 1: The initial state contains NaN"):
        nh.integrate_ensemble(GEARBOX.canonical, METHOD, (q, p), 0.1, 20)


def test_throw_under_jit_is_refused():
    run = jax.jit(lambda y: nh.integrate_ensemble(GEARBOX.canonical, METHOD, y, 0.1, 10).ys)
    with pytest.raises(ValueError, match="throw=False"):
        run(_states(2))


@pytest.mark.parametrize(
    ("y0s", "dt", "match"),
    [
        ((jnp.zeros(3), jnp.zeros(3)), 0.1, "leading batch axis: q must be a 1-D array"),
        ((jnp.zeros((2, 3)), jnp.zeros((3, 3))), 0.1, "same non-zero batch size"),
        ((jnp.zeros((2, 3)), jnp.zeros((2, 4))), 0.1, "leading batch axis: q and p must have the same shape"),
        (_states(2), -0.1, "dt must be positive"),
    ],
)
def test_bad_input(y0s, dt, match):
    with pytest.raises(ValueError, match=match):
        nh.integrate_ensemble(GEARBOX.canonical, METHOD, y0s, dt, 10)


def test_compiles_once_for_new_step_sizes_start_times_and_checks():
    """dt, t0 and check_constraint reach the sharded program as arrays: a run that
    changes only them compiles nothing again (a chunked run's later chunks change t0
    and drop the check), and its numbers are those of a fresh `integrate`."""
    run = nh._ensemble._sharded_run._cached
    states = _states(2)
    nh.integrate_ensemble(GEARBOX.canonical, METHOD, states, 0.1, 10)
    programs = run._cache_size()
    later = nh.integrate_ensemble(GEARBOX.canonical, METHOD, states, 0.05, 10, t0=3.0, check_constraint=False)
    assert run._cache_size() == programs
    alone = nh.integrate(GEARBOX.canonical, METHOD, jax.tree.map(lambda y: y[1], states), 0.05, 10, t0=3.0)
    np.testing.assert_allclose(later.ts[1], alone.ts, rtol=1e-15)
    assert _max_difference(jax.tree.map(lambda y: y[1], later.ys), alone.ys) <= 1e-13


def test_a_device_named_twice_is_refused():
    device = jax.devices()[0]
    with pytest.raises(ValueError, match=f"devices must be distinct .*repeated: {device}"):
        nh.integrate_ensemble(GEARBOX.canonical, METHOD, _states(2), 0.1, 10, devices=[device, device])


_TWO_DEVICES = textwrap.dedent(
    """
    import json
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import nhjax as nh

    gearbox = nh.examples.gearbox()
    method = nh.GonzalezF()
    out = dict(devices=len(jax.devices()))
    for count in (4, 5):
        states = jax.vmap(gearbox.random_initial_state)(jax.random.split(jax.random.key(1), count))
        sharded = nh.integrate_ensemble(gearbox.canonical, method, states, 0.1, 40, save_every=10)
        alone = jax.vmap(lambda y: nh.integrate(gearbox.canonical, method, y, 0.1, 40, save_every=10))(states)
        leaves = zip(jax.tree.leaves((sharded.ys, sharded.energy)), jax.tree.leaves((alone.ys, alone.energy)))
        out[count] = dict(
            difference=max(float(jnp.max(jnp.abs(a - b))) for a, b in leaves),
            shape=list(sharded.ys[0].shape),
            devices_holding=len(sharded.ys[0].sharding.device_set),
            spec=list(sharded.ys[0].sharding.spec),
        )
    from nhjax._runner import run_chunked
    import pathlib, tempfile
    states = jax.vmap(gearbox.random_initial_state)(jax.random.split(jax.random.key(1), 4))
    directory = pathlib.Path(tempfile.mkdtemp()) / "chunks"
    programs = nh._ensemble._sharded_run._cached._cache_size()
    chunked = run_chunked(gearbox.canonical, method, states, 0.1, 40, directory=directory, save_every=10, chunk_steps=20, progress=False)
    alone = jax.vmap(lambda y: nh.integrate(gearbox.canonical, method, y, 0.1, 40, save_every=10))(states)
    try:
        run_chunked(gearbox.canonical, method, states, 0.1, 40, directory=directory, save_every=10, chunk_steps=20, progress=False, devices=jax.devices()[:1])
        refused = ""
    except ValueError as error:
        refused = str(error)
    out["chunked"] = dict(
        difference=max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(chunked.ys), jax.tree.leaves(alone.ys))),
        shape=list(chunked.ys[0].shape),
        manifest_devices=json.loads((directory / "manifest.json").read_text()).get("devices"),
        programs=nh._ensemble._sharded_run._cached._cache_size() - programs,
        refused=refused,
    )
    print(json.dumps(out))
    """
)


def test_two_cpu_devices_give_the_unsharded_result():
    """A fresh process with two CPU devices: the batch split over both (even, and odd
    with padding) gives the numbers of one `vmap` on one device, by `integrate_ensemble`
    and by `run_chunked`."""
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    environment = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu")
    completed = subprocess.run(
        [sys.executable, "-c", _TWO_DEVICES], env=environment, capture_output=True, text=True, timeout=600
    )
    assert completed.returncode == 0, completed.stderr
    out = json.loads(completed.stdout.strip().splitlines()[-1])
    assert out["devices"] == 2
    for count in ("4", "5"):
        assert out[count]["shape"] == [int(count), 5, 3]
        assert out[count]["difference"] <= 1e-13
    assert out["4"]["devices_holding"] == 2
    assert out["4"]["spec"] == ["batch"]
    # `run_chunked` splits a batch's chunks over both devices: the unchunked numbers to
    # roundoff, one program for both chunks (t0 and the check traced), and the manifest
    # records the split, so that resuming on one device is refused.
    chunked = out["chunked"]
    assert chunked["shape"] == [4, 5, 3]
    assert chunked["difference"] <= 1e-12
    assert chunked["manifest_devices"] == 2
    assert chunked["programs"] == 1
    assert "devices: 2 there, None here" in chunked["refused"]
