"""`nhjax.integrate_ensemble` across the processes of a `jax.distributed` job: two
processes on this machine (coordinator on 127.0.0.1, one CPU device each, gloo CPU
collectives) share a batch, and each gets the whole Solution, equal to a one-process
`vmap`, per-trajectory codes included."""

import socket
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np

import nhjax as nh


PROCESS = textwrap.dedent(
    """
    import sys

    import jax

    process, port, out = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(f"127.0.0.1:{port}", num_processes=2, process_id=process)
    import numpy as np

    import nhjax as nh

    assert len(jax.devices()) == 2 and len(jax.local_devices()) == 1
    quartic = nh.examples.chaotic_quartic(3)
    states = quartic.random_initial_states(jax.random.key(0), 5).at[3, 0].set(np.nan)
    method = nh.DiscreteGradient()
    run = dict(dt=0.1, n_steps=200, save_every=50)
    whole = nh.integrate_ensemble(quartic.adapted, method, states, throw=False, **run)
    try:
        nh.integrate_ensemble(quartic.adapted, method, states, **run)
        raised = ""
    except RuntimeError as error:
        raised = str(error)
    sharded = nh.integrate_ensemble(quartic.adapted, method, states[:4], throw=False, gather=False, **run)
    own = [shard.data.shape[0] for shard in sharded.ys.addressable_shards]
    try:
        nh.integrate_ensemble(quartic.adapted, method, states, throw=False, gather=False, **run)
        refused = ""
    except ValueError as error:
        refused = str(error)
    np.savez(
        out, ys=np.asarray(whole.ys), energy=np.asarray(whole.energy),
        result=np.asarray(whole.result._value), raised=raised, own=np.asarray(own), refused=refused,
    )
    """
)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_two_processes_each_get_the_one_process_result(tmp_path):
    script = tmp_path / "process.py"
    script.write_text(PROCESS)
    port = str(_free_port())
    outs = [tmp_path / f"process{index}.npz" for index in range(2)]
    processes = [
        subprocess.Popen(
            [sys.executable, str(script), str(index), port, str(out)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        for index, out in enumerate(outs)
    ]
    for process in processes:
        output, _ = process.communicate(timeout=600)
        assert process.returncode == 0, output[-3000:]

    quartic = nh.examples.chaotic_quartic(3)
    states = quartic.random_initial_states(jax.random.key(0), 5).at[3, 0].set(jnp.nan)
    single = jax.vmap(
        lambda x: nh.integrate(quartic.adapted, nh.DiscreteGradient(), x, 0.1, 200, save_every=50, throw=False)
    )(states)
    expected_codes = np.asarray(single.result._value)
    assert expected_codes[3] != 0 and np.all(np.delete(expected_codes, 3) == 0)
    for out in outs:
        with np.load(out) as saved:
            np.testing.assert_array_equal(saved["result"], expected_codes)
            # Rounding, not bits: each process vectorises a batch of another size.
            np.testing.assert_allclose(saved["ys"], single.ys, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(saved["energy"], single.energy, rtol=1e-12, atol=1e-12)
            assert "1 of 5 trajectories failed; trajectory 3: The initial state contains NaN" in str(saved["raised"])
            assert saved["own"].tolist() == [2]  # gather=False: each process holds its half
            assert "multiple of the 2 devices, got 5" in str(saved["refused"])
