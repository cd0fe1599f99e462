"""A `lax.scan` run as an outer scan over chunks of its steps (`scan_in_chunks`), for
XLA:CPU's benefit: the recording and the replay of a run's derivatives
(`nhjax._replay`)."""

import math

import jax
import jax.lax as lax
import jax.numpy as jnp

from ._linalg import SEQUENTIAL_BYTES


def tree_bytes(tree) -> int:
    """The bytes of the arrays (or their shapes) in `tree`."""
    return sum(
        math.prod(leaf.shape) * jnp.dtype(leaf.dtype).itemsize
        for leaf in jax.tree.leaves(tree)
        if hasattr(leaf, "dtype")
    )


def largest_array_bytes(tree) -> int:
    """The bytes of the largest array (or shape) in `tree`."""
    return max((tree_bytes(leaf) for leaf in jax.tree.leaves(tree)), default=0)


def chunk_length(length: int, row_bytes: int) -> int:
    """The steps of a chunk of `scan_in_chunks`: the largest divisor of `length` for
    which that many rows of `row_bytes` hold at most `SEQUENTIAL_BYTES` (1: no
    chunks)."""
    most = max(1, SEQUENTIAL_BYTES // max(row_bytes, 1))
    return max(c for c in range(1, min(most, length) + 1) if length % c == 0)


def scan_in_chunks(body, init, xs, row_bytes: int):
    """`lax.scan(body, init, xs)`, as an outer scan over chunks of consecutive steps,
    each an inner scan of `chunk_length` steps, where `row_bytes` is a step's row of
    the largest array stacked over the steps: of the inputs and outputs, and in
    reverse mode of what is kept per step.

    A scan's body reads and writes the whole stacked arrays, all the steps' rows, and
    XLA:CPU then hands each of its operations to its thread pool
    (`nhjax._linalg.SEQUENTIAL_BYTES`, a bound on each array), whose scheduling costs
    more than a small step's operations: an inner scan's body reads and writes a
    chunk's rows, and runs its operations one after another where its other arrays
    are small too (`benchmarks/gradients.py --parts` times the recording and the
    reversed replay of a derivative). The steps and their order are those of the plain
    scan, and so are the results; a length with no divisor in that bound (a prime
    number of steps) is scanned whole.

    Not for a run's own loop of saves (`nhjax._fixed_steps`), whose steps run in a
    loop of their own: saving every step of 2 000, chunks of saves made the sleigh's
    program 241 distinct fused computations against 234, a compilation that only runs
    of some hundreds of thousands of steps repay in the time they save."""
    length = jax.tree.leaves(xs)[0].shape[0]
    chunk = chunk_length(length, row_bytes)
    if chunk in (1, length):
        return lax.scan(body, init, xs)
    chunks = jax.tree.map(lambda x: x.reshape(length // chunk, chunk, *x.shape[1:]), xs)
    carry, ys = lax.scan(lambda carry, rows: lax.scan(body, carry, rows), init, chunks)
    return carry, jax.tree.map(lambda y: y.reshape(length, *y.shape[2:]), ys)
