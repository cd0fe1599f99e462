"""Ensemble speed-up from splitting a batch over devices (`nhjax.integrate_ensemble`).

One process with `--devices` CPU devices (XLA's `--xla_force_host_platform_device_count`,
set here before JAX starts) times the same batch of gearbox trajectories with GONZALEZ-R
on the first device alone and on all of them, and checks that both give the same
numbers. On a machine with several accelerators, pass `--platform gpu` to use them
instead.

Run: python benchmarks/sharding.py [--devices 2] [--batch 200] [--steps 200] [--repeats 3]
Prints one JSON line; the suite (benchmarks/suite.py) stores it.
"""

import argparse
import json
import os


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--devices", type=int, default=2)
    parser.add_argument("--batch", type=int, default=200)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--platform", default="cpu")
    options = parser.parse_args()
    if options.platform == "cpu":
        os.environ["XLA_FLAGS"] = (
            os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={options.devices}"
        )
    os.environ["JAX_PLATFORMS"] = options.platform

    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import nhjax as nh
    from _timing import run_and_time

    devices = jax.devices()[: options.devices]
    gearbox = nh.examples.gearbox()
    states = jax.vmap(gearbox.random_initial_state)(jax.random.split(jax.random.key(1), options.batch))

    def run(on):
        return nh.integrate_ensemble(
            gearbox.canonical, nh.GonzalezR(), states, 0.1, options.steps, save_every=options.steps, devices=on
        )

    seconds, finals = {}, {}
    for label, on in (("one_device", devices[:1]), ("all_devices", devices)):
        solution, seconds[label] = run_and_time(run, on, repeats=options.repeats)
        finals[label] = solution.ys
    difference = max(
        float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
        for a, b in zip(jax.tree.leaves(finals["one_device"]), jax.tree.leaves(finals["all_devices"]))
    )
    trajectory_steps = options.batch * options.steps
    print(json.dumps(dict(
        devices=len(devices),
        platform=options.platform,
        batch=options.batch,
        steps=options.steps,
        repeats=options.repeats,
        seconds=seconds,
        trajectory_steps_per_s={label: trajectory_steps / s for label, s in seconds.items()},
        speedup=seconds["one_device"] / seconds["all_devices"],
        max_difference=difference,
    )))


if __name__ == "__main__":
    main()
