"""A scan in chunks of its steps (`nhjax._chunked_scan`)."""

import jax
import jax.numpy as jnp
import pytest

from nhjax._chunked_scan import chunk_length, scan_in_chunks

from .helpers import equations


def _body(carry, x):
    carry = jnp.sin(carry) + x[0] * carry[::-1]
    return carry, (carry * x[1], jnp.sum(carry))


@pytest.mark.parametrize("length, chunk", [(12, 4), (13, 1), (4, 4)])
def test_a_scan_in_chunks_is_the_plain_scan(length, chunk):
    """The carry and the stacked outputs of the plain scan, bitwise, from an outer scan
    over chunks of steps, each an inner scan, where a step's row of the largest array
    has 100 bytes: 12 steps in chunks of 4 (5 rows would exceed `SEQUENTIAL_BYTES`);
    one plain scan where no divisor of the length fits but 1 (13 steps) or all of it
    does (4 steps)."""
    init = jnp.array([0.3, -1.2, 0.7])
    xs = jnp.linspace(-1.0, 1.0, 2 * length).reshape(length, 2)
    assert chunk_length(length, 100) == chunk
    want = jax.lax.scan(_body, init, xs)
    got = jax.jit(lambda init, xs: scan_in_chunks(_body, init, xs, row_bytes=100))(init, xs)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        assert a.shape == b.shape and bool(jnp.all(a == b))
    jaxpr = jax.make_jaxpr(lambda init, xs: scan_in_chunks(_body, init, xs, row_bytes=100))(init, xs).jaxpr
    scans = [e for e in equations(jaxpr) if e.primitive.name == "scan"]
    assert len(scans) == (2 if 1 < chunk < length else 1)
