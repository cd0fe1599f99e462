"""How a fixed-step run is differentiated: by replay from its stored roots
(`nhjax._replay`) where that fits the memory budget, by diffrax's checkpointed adjoint
otherwise."""

import diffrax
import jax

from ._ledger import run_start
from ._chunked_scan import tree_bytes
from ._replay import replay_storage_bytes
from ._solver.base import AbstractMethod


def checked_adjoint(adjoint: diffrax.AbstractAdjoint | None) -> diffrax.AbstractAdjoint | None:
    if adjoint is not None and not isinstance(adjoint, diffrax.AbstractAdjoint):
        raise ValueError(f"adjoint must be a diffrax adjoint, got {adjoint!r}.")
    return adjoint


def adjoint_or_default(adjoint: diffrax.AbstractAdjoint | None) -> diffrax.AbstractAdjoint:
    adjoint = checked_adjoint(adjoint)
    return diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint


# What one trajectory's checkpoints may occupy when every step keeps one.
CHECKPOINT_BUDGET_BYTES = 32 * 2**20


def default_adjoint(system, method, y0, args, dt, n_steps: int) -> diffrax.RecursiveCheckpointAdjoint:
    r"""The reverse-mode adjoint of a fixed-step run whose derivatives are not replayed
    from stored roots (`replays_derivatives`: a diffrax solver, a composition, or a run
    too long for the budget): a checkpoint at every step where `n_steps` checkpoints of
    the state and the method's solver state fit in `CHECKPOINT_BUDGET_BYTES` (per
    trajectory: under `vmap` a batch of $B$ takes $B$ times as much), otherwise
    diffrax's $O(\log n)$ checkpoints.

    With a checkpoint at every step the backward pass runs each step once more, then
    the transpose of its linearisation; with $c < n$ checkpoints it first recomputes
    steps from the nearest checkpoint, $O(n\log n)$ steps in all for $c = O(\log n)$.
    `python benchmarks/gradients.py` measures them against the forward run."""
    y0 = run_start(system, y0)
    solver_state = jax.eval_shape(lambda: method.init(system, 0 * dt, dt, y0, args))
    if n_steps * tree_bytes((y0, solver_state)) <= CHECKPOINT_BUDGET_BYTES:
        return diffrax.RecursiveCheckpointAdjoint(checkpoints=n_steps)
    return diffrax.RecursiveCheckpointAdjoint()


def replays_derivatives(system, method, y0, args, dt, n_steps: int, bounded: bool = False) -> bool:
    """Whether the derivatives of a run without a given `adjoint` come from its stored
    roots (`nhjax._replay`): for an nhjax method (`nhjax._solver.base.AbstractMethod`)
    whose roots and replayed states for `n_steps` steps fit in
    `CHECKPOINT_BUDGET_BYTES` per trajectory; otherwise `default_adjoint`."""
    if not isinstance(method, AbstractMethod):
        return False
    return n_steps * replay_storage_bytes(system, method, y0, args, dt, bounded) <= CHECKPOINT_BUDGET_BYTES
