"""What the `nhjax` command's persistent compilation cache (`_nhjax_command.use_compilation_cache`)
saves: wall seconds of one command, each run a process of its own, as a user runs it.

Three ways, taken in turn in each repeat so that the machine's drift falls on all alike,
each repeat in a fresh `XDG_CACHE_HOME`: `off` (`JAX_ENABLE_COMPILATION_CACHE=false`,
which writes nothing), `cold` (the empty cache folder, which the run fills) and `warm`
(the folder the cold run just filled). The command's XLA flag probe is answered once
beforehand and its answers copied into each fresh folder, so that no run pays for it.
Medians over `--repeats`, the ratios warm/off and cold/off, and the size of the filled
cache.

Run: python benchmarks/compilation_cache.py [--repeats R] [--command "simulate disk-3d ..."]
Results go to benchmarks/results/compilation_cache.json.
"""

import os
import pathlib
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

from _timing import options, write


COMMAND = "simulate disk-3d --method gonzalez-r --dt 0.01 --t1 10 --no-progress"


def _nhjax(arguments: list[str], environment: dict, out: pathlib.Path) -> float:
    """Seconds for one `nhjax` command in its own process, through the command's entry point."""
    program = "import sys, _nhjax_command; sys.exit(_nhjax_command.main(sys.argv[1:]))"
    extra = ["--out", str(out)] if arguments[0] == "simulate" else []
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", program, *arguments, *extra], env=environment, check=True, capture_output=True)
    return time.perf_counter() - start


def main():
    arguments = options(__doc__, "compilation_cache", repeats=3, command=COMMAND)
    command = shlex.split(arguments.command)
    base = {name: value for name, value in os.environ.items() if not name.startswith("JAX_COMPILATION_CACHE")}
    with tempfile.TemporaryDirectory() as scratch:
        scratch = pathlib.Path(scratch)
        flags = scratch / "flags"
        # Answer the command's XLA flag probe once, for every run below.
        _nhjax(command, dict(base, XDG_CACHE_HOME=str(flags), JAX_ENABLE_COMPILATION_CACHE="false"), scratch / "x.npz")
        seconds = {"off": [], "cold": [], "warm": []}
        size_mib = []
        for repeat in range(arguments.repeats):
            home = scratch / f"home{repeat}"
            shutil.copytree(flags, home)
            environments = {
                "off": dict(base, XDG_CACHE_HOME=str(home), JAX_ENABLE_COMPILATION_CACHE="false"),
                "cold": dict(base, XDG_CACHE_HOME=str(home)),
                "warm": dict(base, XDG_CACHE_HOME=str(home)),
            }
            for way, environment in environments.items():
                seconds[way].append(_nhjax(command, environment, scratch / f"{way}.npz"))
            cache = home / "nhjax" / "compilation"
            size_mib.append(sum(path.stat().st_size for path in cache.iterdir()) / 2**20)
            print(f"repeat {repeat}: " + ", ".join(f"{way} {values[-1]:.1f} s" for way, values in seconds.items()), flush=True)
    medians = {way: statistics.median(values) for way, values in seconds.items()}
    ratios = {"warm_over_off": medians["warm"] / medians["off"], "cold_over_off": medians["cold"] / medians["off"]}
    print(
        f"nhjax {arguments.command}: median off {medians['off']:.1f} s, cold {medians['cold']:.1f} s, "
        f"warm {medians['warm']:.1f} s; warm/off {ratios['warm_over_off']:.2f}, cold/off {ratios['cold_over_off']:.2f}; "
        f"cache {statistics.median(size_mib):.1f} MiB"
    )
    write(
        dict(
            command=arguments.command,
            repeats=arguments.repeats,
            seconds=seconds,
            median_seconds=medians,
            ratios=ratios,
            cache_mib=statistics.median(size_mib),
        ),
        arguments.out,
    )


if __name__ == "__main__":
    main()
