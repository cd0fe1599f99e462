import jax
import pytest


jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Each module compiles its own programs; dropping them afterwards keeps the memory
    of one long test process bounded."""
    yield
    jax.clear_caches()
