r"""A forced system's state in a run, with its energy ledger: the work the force has
supplied and the energy the dissipation has removed since the run's start.

A run of a system with a force or a dissipation (`AbstractSystem.is_forced`) carries
the ledger beside the state (`Ledgered`), so that the energy balance
$H(y_k) - H(y_0) = W_k - D_k$ can be checked at every save. An nhjax method adds to it
what its own step supplied and removed (`nhjax._solver.base.AbstractMethod.exchange`,
exact to roundoff for the discrete-gradient methods); a diffrax solver integrates the
ledger's rates with the state, to its own order: on a `Ledgered` state a system's
vector field is the state's field and the ledger's rates, the power supplied and
dissipated (`AbstractSystem.vf`, `AbstractSystem.power`)."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree


class Ledgered(eqx.Module):
    """The state of a forced run: the system's `state`, the `work` supplied by the
    force and the energy `dissipated` by the dissipation since the run's start (or,
    for a vector field, their rates)."""

    state: PyTree[Array]
    work: Float[Array, ""]
    dissipated: Float[Array, ""]

    def after(self, state: PyTree[Array], supplied: Array, dissipated: Array) -> "Ledgered":
        """The ledger after a step to `state` that supplied and dissipated these."""
        return Ledgered(state, self.work + supplied, self.dissipated + dissipated)


def unledgered(y: PyTree[Array] | Ledgered) -> PyTree[Array]:
    """The system's state in a run's state, ledgered or not."""
    return y.state if isinstance(y, Ledgered) else y


def run_start(system, y0: PyTree[Array]) -> PyTree[Array] | Ledgered:
    """A run's initial state: `y0`, with an empty ledger for a forced system."""
    if not system.is_forced():
        return y0
    zero = jnp.zeros((), jax.tree.leaves(y0)[0].dtype)
    return Ledgered(y0, zero, zero)


def observe(system):
    """The saves of a run of `system`: `save(t, y, args) -> (state, observables)`, the
    state without its ledger, whose entries, `work` and `dissipated`, join the
    system's observables."""

    def save(t, y, args):
        del t
        if isinstance(y, Ledgered):
            ledger = {"work": y.work, "dissipated": y.dissipated}
            return y.state, {**system.observables(y.state, args), **ledger}
        return y, system.observables(y, args)

    return save
