r"""Peer baselines in plain NumPy + SciPy (no JAX): the way existing Python codes
integrate a nonholonomic system, for timing next to nhjax.

- `gonzalez_r_numpy`: GONZALEZ-R (§3.3) with the paper's central-difference $\partial X/\partial q$,
  one `scipy.optimize.fsolve` per step;
- `solve_ivp_run`: the index-1 ODE (multiplier eliminated) with `scipy.integrate.solve_ivp`.

Both systems have $M = I$, $H = \tfrac12|p|^2 + V(q)$ and one constraint $A(q)p = 0$,
$A$ of shape $(1, n)$. Gradients and $\partial A/\partial q$ are written out by hand.
"""

import dataclasses
import time
from collections.abc import Callable

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import fsolve


@dataclasses.dataclass(frozen=True)
class Problem:
    """$H = \\tfrac12|p|^2 + V(q)$ with constraints $A(q)p = 0$; `constraint_drift(q, v)`
    is $\\partial A/\\partial q[v]\\,v$, shape (k,)."""

    name: str
    n: int
    potential: Callable
    grad_potential: Callable
    constraints: Callable
    constraint_drift: Callable

    def hamiltonian(self, q, p):
        return 0.5 * p @ p + self.potential(q)


GEARBOX = Problem(
    name="gearbox",
    n=3,
    potential=lambda q: 0.5 * (q[0] ** 2 + q[1] ** 2) + np.cos(q[2]) - 0.2 * np.sin(2 * q[2]),
    grad_potential=lambda q: np.array([q[0], q[1], -np.sin(q[2]) - 0.4 * np.cos(2 * q[2])]),
    constraints=lambda q: np.array([[1.0, np.sin(q[2]), 0.0]]),
    constraint_drift=lambda q, v: np.array([np.cos(q[2]) * v[2] * v[1]]),
)


def quartic(pairs: int) -> Problem:
    """The chaotic quartic of §4.1 with `pairs` = N: $q = (x, w_{1..N}, z_{1..N})$,
    $V = \\tfrac12(|q|^2 + z_1^2z_2^2 + \\sum_i w_i^2z_i^2)$ (no $z_1^2z_2^2$ for N = 1),
    $A = [1, 0_N, w^T]$."""
    n = 2 * pairs + 1
    w_, z_ = slice(1, pairs + 1), slice(pairs + 1, n)

    def potential(q):
        w, z = q[w_], q[z_]
        coupling = z[0] ** 2 * z[1] ** 2 if pairs >= 2 else 0.0
        return 0.5 * (q @ q + coupling + w**2 @ z**2)

    def grad_potential(q):
        w, z = q[w_], q[z_]
        grad = q.copy()
        grad[w_] += w * z**2
        grad[z_] += w**2 * z
        if pairs >= 2:
            grad[pairs + 1] += z[0] * z[1] ** 2
            grad[pairs + 2] += z[0] ** 2 * z[1]
        return grad

    def constraints(q):
        return np.concatenate([[1.0], np.zeros(pairs), q[w_]])[None, :]

    def constraint_drift(q, v):
        return np.array([v[w_] @ v[z_]])

    return Problem(f"quartic{pairs}", n, potential, grad_potential, constraints, constraint_drift)


QUARTIC3 = quartic(3)


# GONZALEZ-R.


def _frames(problem, points):
    r"""$X(q)$ for each row of `points`: the last $m$ columns of $Q$ in a Householder QR
    of $A(q)^T$, one batched LAPACK call. The first entry of $A^T$ is 1 for both systems,
    so LAPACK's sign choice never flips and the frames form one smooth field."""
    a_t = np.stack([problem.constraints(q).T for q in points])
    return np.linalg.qr(a_t, mode="complete")[0][:, :, a_t.shape[2]:]


def _reduced_hamiltonian(problem, zeta):
    r"""$\mathcal{H}(q, \rho) = H(q, X(q)\rho)$, (ptoptilde) with $M = I$."""
    q, rho = zeta[: problem.n], zeta[problem.n :]
    return problem.hamiltonian(q, _frames(problem, [q])[0] @ rho)


def _structure_and_gradient(problem, zeta, eps):
    r"""$\Pi(\zeta)$ of (PiMat) with the block (skewMat),
    $B_{ab} = p^T(\partial X_a[X_b] - \partial X_b[X_a])$, and $\nabla\mathcal{H}(\zeta)$ of
    (eq:Htgrad): $\partial_\rho\mathcal{H} = y = \rho$,
    $\partial_{q_i}\mathcal{H} = \partial_{q_i}V - p^T\,\partial_iX\,y$, $p = X\rho$, with
    $\partial_iX = (X(q + \epsilon e_i) - X(q - \epsilon e_i))/2\epsilon$."""
    n = problem.n
    q, rho = zeta[:n], zeta[n:]
    offsets = eps * np.eye(n)
    frames = _frames(problem, np.concatenate([q[None], q + offsets, q - offsets]))
    frame = frames[0]
    derivative = (frames[1 : n + 1] - frames[n + 1 :]) / (2 * eps)  # [i, j, a] = d X_ja / d q_i
    p = frame @ rho
    along = np.einsum("j,ija,ib->ab", p, derivative, frame)  # p^T dX_a[X_b]
    structure = np.block([[np.zeros((n, n)), frame], [-frame.T, along - along.T]])
    grad_q = problem.grad_potential(q) - np.einsum("j,ija,a->i", p, derivative, rho)
    return structure, np.concatenate([grad_q, rho])


def gonzalez_r_numpy(problem, q0, p0, h, n_steps, xtol=1e-13) -> dict:
    r"""GONZALEZ-R: (ptildetop) $\rho = X(q)^T p$, then per step (E-int)
    $\zeta' - \zeta = h\,\Pi(\bar\zeta)\,\bar\nabla\mathcal{H}(\zeta, \zeta')$ with the
    Gonzalez discrete gradient (gonzales)
    $\bar\nabla\mathcal{H} = \nabla\mathcal{H}(\bar\zeta) + \frac{\mathcal{H}(\zeta') -
    \mathcal{H}(\zeta) - \nabla\mathcal{H}(\bar\zeta)\cdot d}{|d|^2}d$, $d = \zeta' - \zeta$,
    $\bar\zeta = (\zeta + \zeta')/2$, $\partial X/\partial q$ by central differences with
    $\epsilon = h$; solved by `fsolve` from $\zeta + h\Pi(\zeta)\nabla\mathcal{H}(\zeta)$.
    $p' = X(q')\rho'$ (ptoptilde).

    Returns q, p of shape (n_steps + 1, n), the wall-clock seconds of the loop, and
    `fsolve_calls`, the total residual evaluations."""
    n = problem.n
    q0, p0 = np.asarray(q0, float), np.asarray(p0, float)
    qs, ps = np.empty((n_steps + 1, n)), np.empty((n_steps + 1, n))
    qs[0], ps[0] = q0, p0
    calls = 0
    start = time.perf_counter()
    zeta = np.concatenate([q0, _frames(problem, [q0])[0].T @ p0])
    for step in range(1, n_steps + 1):
        energy = _reduced_hamiltonian(problem, zeta)

        def residual(zeta1):
            structure, gradient = _structure_and_gradient(problem, 0.5 * (zeta + zeta1), h)
            d = zeta1 - zeta
            dd = d @ d
            if dd > 0:
                change = _reduced_hamiltonian(problem, zeta1) - energy
                gradient = gradient + (change - gradient @ d) / dd * d
            return d - h * structure @ gradient

        structure, gradient = _structure_and_gradient(problem, zeta, h)
        guess = zeta + h * structure @ gradient
        zeta, info, ier, message = fsolve(residual, guess, xtol=xtol, full_output=True)
        calls += info["nfev"]
        if ier != 1:
            raise RuntimeError(f"fsolve failed at step {step} of {problem.name}: {message}")
        # The next step starts from zeta' itself: recomputing rho = X^T p from the
        # returned p rounds with a bias that accumulates in H.
        q = zeta[:n]
        qs[step], ps[step] = q, _frames(problem, [q])[0] @ zeta[n:]
    return dict(q=qs, p=ps, seconds=time.perf_counter() - start, fsolve_calls=calls)


def _errors(problem, qs, ps):
    """Relative energy error and absolute constraint residual |A(q) p| per saved state."""
    energies = np.array([problem.hamiltonian(q, p) for q, p in zip(qs, ps)])
    constraint = np.array([np.max(np.abs(problem.constraints(q) @ p)) for q, p in zip(qs, ps)])
    return np.abs(energies - energies[0]) / abs(energies[0]), constraint


def gonzalez_r_drift(problem, q0, p0, h, n_steps) -> dict:
    """`gonzalez_r_numpy` summarised: seconds, max relative energy error and max
    constraint residual over the trajectory."""
    run = gonzalez_r_numpy(problem, q0, p0, h, n_steps)
    energy, constraint = _errors(problem, run["q"], run["p"])
    return dict(
        seconds=run["seconds"],
        max_energy_error=float(energy.max()),
        max_constraint_error=float(constraint.max()),
    )


# The index-1 ODE.


def index1_vector_field(problem) -> Callable:
    r"""$f(t, y)$, $y = (q, p)$: $\dot q = p$, $\dot p = -\nabla V + A^T\lambda$ with
    $AA^T\lambda = A\nabla V - \partial A/\partial q[p]\,p$, from
    $\tfrac{d}{dt}(A(q)p) = 0$ (eq:HamEq with $K = I$)."""
    n = problem.n

    def f(t, y):
        q, p = y[:n], y[n:]
        a, force = problem.constraints(q), problem.grad_potential(q)
        multiplier = np.linalg.solve(a @ a.T, a @ force - problem.constraint_drift(q, p))
        return np.concatenate([p, a.T @ multiplier - force])

    return f


def solve_ivp_run(problem, q0, p0, t1, method, rtol, atol, n_save=1001) -> dict:
    """`solve_ivp` on `index1_vector_field` over [0, t1] (saved at `n_save` evenly
    spaced times). Energy errors are relative, constraint errors |A(q) p|, both at the end
    and as the maximum over the saved times."""
    y0 = np.concatenate([q0, p0]).astype(float)
    times = np.linspace(0.0, t1, n_save)
    start = time.perf_counter()
    solution = solve_ivp(
        index1_vector_field(problem), (0.0, t1), y0, method=method, t_eval=times, rtol=rtol, atol=atol
    )
    seconds = time.perf_counter() - start
    if not solution.success:
        raise RuntimeError(f"solve_ivp {method} failed on {problem.name}: {solution.message}")
    energy, constraint = _errors(problem, solution.y[: problem.n].T, solution.y[problem.n :].T)
    return dict(
        seconds=seconds,
        final_energy_error=float(energy[-1]),
        max_energy_error=float(energy.max()),
        final_constraint_error=float(constraint[-1]),
        max_constraint_error=float(constraint.max()),
        nfev=int(solution.nfev),
    )
