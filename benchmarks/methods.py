"""Every method for NonholonomicSystem side by side, on the gearbox and on the n = 3
chaotic quartic (canonical form) at h = 0.1: µs/step for one trajectory, root-finder
iterations/step, compile time, and trajectory-steps/s for a vmapped batch of 200. The
non-geometric baseline (the index-1 ODE by Tsit5 at the same fixed step) is timed beside
them.

Run: python benchmarks/methods.py [--steps N] [--repeats R]
Figures are medians over repeats, all from one run; results go to
benchmarks/results/methods.json.
"""

import argparse
import pathlib

import diffrax
import jax


jax.config.update("jax_enable_x64", True)

import nhjax as nh  # noqa: E402
from _timing import batch_rate, per_step, write  # noqa: E402


METHODS = {
    "GONZALEZ-R": nh.GonzalezR(),
    "GONZALEZ-F": nh.GonzalezF(),
    "SI-DLA": nh.SIDLA(),
    "I-DLA": nh.IDLA(),
    "SPARK": nh.SPARK(),
    "Tsit5 (index-1, baseline)": diffrax.Tsit5(),
}


def _systems(batch):
    gearbox = nh.examples.gearbox()
    quartic = nh.examples.chaotic_quartic(3)
    gearbox_states = jax.vmap(gearbox.random_initial_state)(jax.random.split(jax.random.key(1), batch))
    quartic_states = jax.vmap(quartic.from_adapted)(quartic.random_initial_states(jax.random.key(1), batch))
    return {
        "gearbox": (gearbox.canonical, gearbox.random_initial_state(jax.random.key(0)), gearbox_states),
        "quartic_n3": (quartic.canonical, quartic.from_adapted(quartic.initial_state(0.7)), quartic_states),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=10_000)
    parser.add_argument("--batch-steps", type=int, default=500)
    parser.add_argument("--batch", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "methods.json"))
    options = parser.parse_args()

    results = dict(h=0.1, repeats=options.repeats, batch=options.batch)
    for system_name, (system, y0, states) in _systems(options.batch).items():
        rows = {}
        for name, method in METHODS.items():
            us, compile_s, iterations = per_step(system, method, y0, options.steps, options.repeats)
            rate = batch_rate(system, method, states, options.batch_steps, options.repeats)
            rows[name] = dict(
                us_per_step=us, compile_s=compile_s, root_find_iterations_per_step=iterations,
                batch_trajectory_steps_per_s=rate,
            )
            its = "" if iterations is None else f", {iterations:.2f} iterations/step"
            print(f"{system_name:10s} {name:26s}: {us:8.2f} µs/step{its}, compile {compile_s:5.2f} s, "
                  f"batch {rate:9.3e} trajectory-steps/s")
        results[system_name] = rows
    write(results, options.out)


if __name__ == "__main__":
    main()
