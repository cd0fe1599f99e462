"""The `nhjax` command's entry point, outside the `nhjax` package: importing the package
imports JAX, XLA and every method, which takes seconds (more on a loaded machine), and a
Ctrl-C in that time would end the command with a traceback. This module installs the
command's interrupt handler first, chooses XLA's flags for the command
(`add_xla_flags`), then imports the package (`nhjax._cli.main`)."""

import importlib.metadata
import importlib.util
import json
import os
import pathlib
import signal
import subprocess
import sys
import threading


# XLA:CPU's loop emitter in place of its default MLIR fusion emitters: nhjax's programs,
# many small fusions, compile in about two thirds of the time and run as fast
# (`nhjax reproduce --quick`: 180 s against 235 s, every figure agreeing either way).
# XLA flags are global to a process, so the package never sets them; the command, a
# process of its own, does, unless `XLA_FLAGS` already chooses the emitters.
LOOP_EMITTER = "--xla_cpu_use_fusion_emitters=false"
# XLA:CPU compiles a while loop whose arrays are all small (by default, below about a
# kilobyte) into one function, and otherwise runs its body operation by operation, each
# dispatched on its own: an nhjax step, a few hundred tiny operations, costs more in
# dispatch than in arithmetic. Raised this far, the limit takes in every loop of
# nhjax's programs. Timed in one process each (`XLA_FLAGS` set, then not): 2 000
# GONZALEZ-R steps of Euler's disk, 10.9 us a step against 26.3; the reverse-mode
# derivative through 2 000 steps of the sleigh, 0.039 s against 0.096 s; `nhjax
# reproduce --quick`, 138 s against 150 s, one run after the other, every figure
# agreeing both ways. As `LOOP_EMITTER`, set by the command unless `XLA_FLAGS` sets
# `--xla_backend_extra_options` already.
WHOLE_LOOPS = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000000"


# The most disk the command's compiled programs take in JAX's persistent compilation
# cache (`use_compilation_cache`); JAX evicts the least recently used beyond it.
COMPILATION_CACHE_BYTES = 2**30


def use_compilation_cache() -> None:
    """Keep the programs the command compiles, from one run to the next, in JAX's
    persistent compilation cache: in `compilation_cache()`, unless
    `JAX_COMPILATION_CACHE_DIR` names a folder already (the command then uses that one),
    at most `COMPILATION_CACHE_BYTES` unless `JAX_COMPILATION_CACHE_MAX_SIZE` says
    otherwise; `JAX_ENABLE_COMPILATION_CACHE=false` turns it off. Most of a short run
    is compilation, which a rerun of the same system and method (a resumed run, another
    step size or end time, `nhjax reproduce` again) then reads back
    (`benchmarks/compilation_cache.py` times a command without the cache, filling it and
    reading it). JAX caches only programs
    that took a second or more to compile (`JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS`),
    keyed by the program, XLA's flags and the versions of JAX and XLA, so a changed
    program or install compiles anew. The package itself never sets it: JAX's
    configuration is the user's. Set through the environment, before JAX starts, so the
    command's child processes (`nhjax reproduce`'s figures) share it; a folder that
    cannot be made leaves the command without the cache."""
    if "JAX_COMPILATION_CACHE_DIR" in os.environ:
        return
    directory = compilation_cache()
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError:
        return
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(directory)
    # JAX evicts with file locks from `filelock` (a dependency of nhjax); without it a
    # bound makes every cache read fail with a warning.
    if importlib.util.find_spec("filelock") is not None:
        os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(COMPILATION_CACHE_BYTES))


def compilation_cache() -> pathlib.Path:
    """Where `use_compilation_cache` keeps compiled programs: `compilation/` beside
    `flag_cache()`."""
    return flag_cache().parent / "compilation"


def one_device_per_core() -> list[str]:
    """XLA's flag for one CPU device per core this process may use, where there is more
    than one and neither `JAX_NUM_CPU_DEVICES` nor `XLA_FLAGS` sets the count: XLA:CPU
    otherwise runs a program on one device, one core, and `run_chunked` splits a
    batch's chunks over the devices there are (`nhjax reproduce`'s ensembles of
    Figure 1: on two cores, their runs in a little over half the time). Programs of
    one trajectory run on the first device as before."""
    if "JAX_NUM_CPU_DEVICES" in os.environ:
        return []
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return [f"--xla_force_host_platform_device_count={cores}"] if cores > 1 else []


def xla_knows(flag: str) -> bool:
    """Whether this jaxlib's XLA accepts `flag`: XLA aborts the process on a flag it does
    not know, as versions before the fusion emitters would on `LOOP_EMITTER`, so a child
    process tries it. The child imports JAX, about a second, so the answer is kept for
    this jaxlib version in `flag_cache()`: only the first command after an install
    pays for it. A cache that cannot be read or written only means asking again."""
    try:
        key = f"jaxlib {importlib.metadata.version('jaxlib')} {flag}"
    except importlib.metadata.PackageNotFoundError:
        key = None
    known = _read_flag_cache()
    if key is not None and isinstance(known.get(key), bool):
        return known[key]
    probe = "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"
    environment = dict(os.environ, XLA_FLAGS=flag, JAX_PLATFORMS="cpu")
    knows = subprocess.run([sys.executable, "-c", probe], env=environment, capture_output=True).returncode == 0
    if key is not None:
        _write_flag_cache({**known, key: knows})
    return knows


def flag_cache() -> pathlib.Path:
    """Where `xla_knows` keeps its answers: `$XDG_CACHE_HOME/nhjax`, else
    `~/.cache/nhjax`."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return pathlib.Path(base) / "nhjax" / "xla-flags.json"


def _read_flag_cache() -> dict:
    try:
        known = json.loads(flag_cache().read_text())
    except (OSError, ValueError):
        return {}
    return known if isinstance(known, dict) else {}


def _write_flag_cache(known: dict) -> None:
    path = flag_cache()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # Written aside and moved into place, so that commands started together never
        # read half a file.
        partial = path.with_name(f"{path.name}.{os.getpid()}")
        partial.write_text(json.dumps(known, indent=1, sort_keys=True))
        os.replace(partial, path)
    except OSError:
        pass


def add_xla_flags(wanted: list[str]) -> None:
    """Add each `--name=value` of `wanted` to `XLA_FLAGS` where they do not set `--name`
    already and this XLA knows the flag; before JAX starts XLA. (The command's flags,
    and the test suite's.)"""
    flags = os.environ.get("XLA_FLAGS", "")
    for flag in wanted:
        if flag.split("=")[0] not in flags and xla_knows(flag):
            flags = f"{flags} {flag}".strip()
    os.environ["XLA_FLAGS"] = flags


def _leave_on_interrupt(*_) -> None:
    print("\nnhjax: interrupted", file=sys.stderr, flush=True)
    os._exit(130)


def main(argv=None) -> int:
    """`nhjax._cli.main`, with Ctrl-C handled from the first instruction on: exit status
    130 and one line, whether it comes while the package imports or later. An ignored
    SIGINT (nohup) stays ignored."""
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) not in (
        signal.SIG_IGN,
        None,
    ):
        signal.signal(signal.SIGINT, _leave_on_interrupt)
    add_xla_flags([LOOP_EMITTER, WHOLE_LOOPS, *one_device_per_core()])
    use_compilation_cache()
    from nhjax._cli import main as command

    return command(argv)


if __name__ == "__main__":
    sys.exit(main())
