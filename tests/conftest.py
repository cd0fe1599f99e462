import os

import jax
import pytest


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
