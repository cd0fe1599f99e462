import os
import shutil
import tempfile

from _nhjax_command import add_xla_flags, LOOP_EMITTER

# Most of the suite's time is XLA compiling programs that then run for milliseconds, so
# the suite compiles them to compile fast, with results that differ by roundoff only
# (every tolerance here holds either way; the few long runs ask for full optimisation,
# `helpers.FULL_OPTIMISATION`):
# - XLA's lowest optimisation level;
# - XLA:CPU's loop emitter in place of its MLIR fusion emitters, which halves the
#   compile time of the suite's programs (tests/test_faults.py: 178 s -> 117 s).
# A flag already set in XLA_FLAGS is kept: `XLA_FLAGS=--xla_backend_optimization_level=2
# --xla_cpu_use_fusion_emitters=true` runs the suite on the programs as users' runs
# compile them. Set in the controlling process before JAX starts XLA; the test workers
# and the processes they start inherit it.
if "PYTEST_XDIST_WORKER" not in os.environ:
    add_xla_flags(["--xla_backend_optimization_level=0", LOOP_EMITTER])

import jax  # noqa: E402
import pytest  # noqa: E402


jax.config.update("jax_enable_x64", True)

# Compiled programs are kept from module to module (the small programs of eager
# operations recur in every module, and compiling them again costs about a minute per
# test process), until the process's resident memory passes this bound.
_MEMORY_BOUND_BYTES = 3 * 2**30


def _resident_bytes() -> int | None:
    """This process's resident memory, where /proc tells it (Linux); None elsewhere."""
    try:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


@pytest.fixture(autouse=True, scope="module")
def _bound_the_memory_of_compiled_programs():
    """After each module, drop every compiled program if the process holds more than
    the bound (or if its memory cannot be read): one long test process stays bounded."""
    yield
    resident = _resident_bytes()
    if resident is None or resident > _MEMORY_BOUND_BYTES:
        jax.clear_caches()


_CACHE_DIRECTORY = pytest.StashKey[str]()
_COMPILATION_CACHE_VARIABLES = {
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
    "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0",
}


def pytest_configure(config):
    """One persistent compilation cache for the session, shared by the test processes and
    the processes they start (the command line, resumed runs, the reproduction): a
    program compiled in one is read back in the others instead of compiled again. It
    starts empty and is deleted at the end; a cache directory already set is used as is.
    Set in the controlling process, before the workers start, so they inherit it."""
    if hasattr(config, "workerinput") or "JAX_COMPILATION_CACHE_DIR" in os.environ:
        return
    directory = tempfile.mkdtemp(prefix="nhjax-tests-compilation-cache-")
    config.stash[_CACHE_DIRECTORY] = directory
    os.environ["JAX_COMPILATION_CACHE_DIR"] = directory
    for name, value in _COMPILATION_CACHE_VARIABLES.items():
        os.environ.setdefault(name, value)
    # This process read JAX's configuration when it imported JAX (above), before now.
    jax.config.update("jax_compilation_cache_dir", directory)
    jax.config.update(
        "jax_persistent_cache_min_compile_time_secs", float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"])
    )
    jax.config.update(
        "jax_persistent_cache_min_entry_size_bytes", int(os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"])
    )


def pytest_unconfigure(config):
    directory = config.stash.get(_CACHE_DIRECTORY, None)
    if directory is not None:
        shutil.rmtree(directory, ignore_errors=True)
