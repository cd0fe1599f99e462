r"""GONZALEZ-R's step against variants of itself, timed in one process with the runs
interleaved (A, B, C, A, B, C, ...) so that the machine's drift falls on all alike:

- `GONZALEZ-R`: as shipped (chord matrix with the frame held to first order and
  turned along the velocity, extrapolated predictor, products with the frame
  derivative matrix-free);
- `no frame turn`: the chord matrix with the frame held to first order only
  (`nhjax._reduced.ReducedSystem.field_jacobian` without `frame_turn`);
- `no predictor`: every step starts from no motion, as the first step of a run does
  (the chord iteration's first iterate then a linearly implicit Euler step);
- `exact chord matrix`: the Jacobian of the simplified residual for the chord matrix
  by forward differences (`GonzalezR(exact_chord_matrix=True)`), and
  `jacfwd chord matrix`: the same Jacobian by `jax.jacfwd` (second derivatives of the
  QR), as that option formed it before;
- `formed frame derivative`: $J = \partial_q(X^Tp)$ formed at every residual by
  `jax.jacfwd` through the QR ($n$ tangents), where the method takes the products
  $Jv$ and $J^Tw$ from one linearisation.

On the gearbox, the quartic with n = 3 and n = 10, the synthetic system of
`benchmarks/scaling.py` with n = 16, Euler's disk and a tractor pulling 5 trailers
(n = 8, k = 6: `nhjax.examples.tractor_trailers`) at h = 0.1: median µs/step,
root-finder iterations per step and compile time, and each variant's time as a ratio
to the shipped method's. Every variant forms its chord matrix at every step
(`reuse_chord_matrix=False`), so that the figures compare the steps themselves;
`benchmarks/chord_reuse.py` measures keeping the matrix.

Run: python benchmarks/gonzalez_r_variants.py [--repeats 7] [--problems "5 trailers,gearbox"]
Results go to benchmarks/results/gonzalez_r_variants.json.
"""

import argparse
import json
import pathlib

import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

import nhjax as nh  # noqa: E402
import scaling  # noqa: E402
from _timing import run_and_time_interleaved, timed, write  # noqa: E402
from nhjax._reduced import ReducedSystem  # noqa: E402


class NoPredictor(nh.GonzalezR):
    """Hands the next step no velocities, so every step starts from no motion."""

    def complete(self, u, data):
        y1, carry = super().complete(u, data)
        unknown = jnp.full_like(carry.last_velocity, jnp.nan)
        return y1, carry._replace(last_velocity=unknown, earlier_velocity=unknown)


class _FormedFrameDerivativeReduced(ReducedSystem):
    def at(self, zeta, args, contracted=None):
        if contracted is None:
            contracted = self.formed_frame_derivative(zeta, args)
        return super().at(zeta, args, contracted)


class _NoFrameTurnReduced(ReducedSystem):
    def field_jacobian(self, zeta, t, args, frame_turn=False):
        return super().field_jacobian(zeta, t, args)


class JacfwdChordMatrix(nh.GonzalezR):
    """The exact chord matrix by `jax.jacfwd` through the residual, not by differences."""

    def chord_jacobian(self, u, data):
        return jax.jacfwd(self.simplified_residual)(u, data)


def _on_reduced(reduced_type):
    """GONZALEZ-R with its reduced system of type `reduced_type`."""

    class Variant(nh.GonzalezR):
        def _reduced(self, system, signs, h, y0, args):
            reduced = super()._reduced(system, signs, h, y0, args)
            return reduced_type(system, signs, reduced.derivative, reduced.difference_step, reduced.metric)

    return Variant(reuse_chord_matrix=False)


VARIANTS = {
    "GONZALEZ-R": nh.GonzalezR(reuse_chord_matrix=False),
    "no frame turn": _on_reduced(_NoFrameTurnReduced),
    "no predictor": NoPredictor(reuse_chord_matrix=False),
    "exact chord matrix": nh.GonzalezR(exact_chord_matrix=True, reuse_chord_matrix=False),
    "jacfwd chord matrix": JacfwdChordMatrix(reuse_chord_matrix=False),
    "formed frame derivative": _on_reduced(_FormedFrameDerivativeReduced),
}


def _problems():
    gearbox = nh.examples.gearbox()
    problems = {"gearbox": (gearbox.canonical, gearbox.random_initial_state(jax.random.key(0)), 5000, gearbox.args)}
    for n, steps in ((3, 1000), (10, 100)):
        quartic = nh.examples.chaotic_quartic(n)
        key_q, key_p = jax.random.split(jax.random.key(n))
        q = 0.5 * jax.random.normal(key_q, (2 * n + 1,))
        p = quartic.canonical.project_momentum(q, 0.5 * jax.random.normal(key_p, (2 * n + 1,)))
        problems[f"quartic n = {n}"] = (quartic.canonical, (q, p), steps, quartic.args)
    problems["synthetic n = 16"] = (scaling.SYSTEM, scaling.initial_state(16), 100, None)
    disk = nh.examples.rolling_disk_3d()
    problems["Euler's disk"] = (disk.canonical, disk.state(**scaling.DISK_START), 500, disk.args)
    train = nh.examples.tractor_trailers(5)
    problems["5 trailers"] = (train.canonical, train.initial_state(), 100, train.args)
    return problems


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--problems", default=None, help="comma-separated names of the problems to run (default: all)")
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "gonzalez_r_variants.json"))
    options = parser.parse_args()

    problems = _problems()
    chosen = list(problems) if options.problems is None else options.problems.split(",")
    path = pathlib.Path(options.out)
    # Problems not run this time keep their last results.
    results = json.loads(path.read_text())["problems"] if path.exists() else {}
    for problem in chosen:
        system, y0, steps, args = problems[problem]
        runs, compile_s = {}, {}
        for name, method in VARIANTS.items():
            runs[name] = jax.jit(
                lambda y0, method=method: nh.integrate(system, method, y0, 0.1, steps, args=args, save_every=steps)
            )
            compile_s[name] = timed(lambda y: runs[name].lower(y).compile(), y0)
        solutions, seconds = run_and_time_interleaved(runs, y0, repeats=options.repeats)
        rows = {
            name: dict(
                compile_s=compile_s[name],
                iterations_per_step=float(solutions[name].stats["root_find_steps"]) / steps,
                us_per_step=seconds[name] / steps * 1e6,
            )
            for name in VARIANTS
        }
        for name, row in rows.items():
            row["time_ratio_to_shipped"] = row["us_per_step"] / rows["GONZALEZ-R"]["us_per_step"]
            print(f"{problem:15s} {name:20s} {row['us_per_step']:9.1f} µs/step  x{row['time_ratio_to_shipped']:.2f}  "
                  f"iterations {row['iterations_per_step']:.2f}  compile {row['compile_s']:.1f} s", flush=True)
        results[problem] = dict(steps=steps, variants=rows)
    write(dict(h=0.1, repeats=options.repeats, problems=results), options.out)


if __name__ == "__main__":
    main()
