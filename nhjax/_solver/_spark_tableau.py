r"""Coefficients of additive SPARK methods for the index-2 nonholonomic DAE, and the
Lobatto IIIA-B-C-C*-D family (Jay, SIAM J. Sci. Comput. 20 (1998) 416-446).

Notation: $s$ stages, nodes $c$, weights $b$; a tableau is an $s \times s$ matrix
$(a_{ij})$ applied to one term of the vector field.
"""

import numpy as np
import equinox as eqx


def _coefficients(value, ndim: int, name: str) -> tuple:
    """`value` as nested tuples of Python floats (hashable, so the tableau is static
    and its exact zeros are compile-time constants)."""
    array = np.asarray(value, dtype=float)
    if array.ndim != ndim:
        raise ValueError(
            f"SPARKTableau.{name} must have {ndim} dimension(s), got shape {array.shape}."
        )
    if not np.all(np.isfinite(array)):
        raise ValueError(f"SPARKTableau.{name} must be finite, got {array}.")
    return array.tolist() if ndim == 0 else _nested_tuple(array.tolist())


def _nested_tuple(value):
    return tuple(_nested_tuple(item) for item in value) if isinstance(value, list) else value


class SPARKTableau(eqx.Module):
    r"""The coefficients of an $s$-stage additive SPARK method for
    $\dot q = \partial_p H$, $\dot p = -\partial_q H + A(q)^T\lambda$,
    $0 = g(q, p) := A(q)\,\partial_p H(q, p)$ (see `nhjax.SPARK` for the step):

    - `c`, `b`: nodes and weights, shape `(s,)`, shared by every term;
    - `velocity`: the $(s, s)$ tableau of $\partial_p H$ (the $q$ equation);
    - `force`: the tableau of $-\partial_q H$;
    - `constraint_force`: the tableau of $A(q)^T\lambda$;
    - `constraint_weights`: $(\omega_{ij})$ of shape `(s - 1, s)`, the stage constraint
        equations $\sum_j \omega_{ij}\, g(Q_j, P_j) = 0$, $i = 1, \dots, s - 1$ (the
        $s$-th constraint equation is $g(q_1, p_1) = 0$ at the step's end);
    - `order`: the order of the method, as reported by `SPARK.order`.

    The coefficients are stored as tuples of floats (static fields): shapes and exact
    zeros are known when a step is compiled.
    """

    c: tuple = eqx.field(static=True)
    b: tuple = eqx.field(static=True)
    velocity: tuple = eqx.field(static=True)
    force: tuple = eqx.field(static=True)
    constraint_force: tuple = eqx.field(static=True)
    constraint_weights: tuple = eqx.field(static=True)
    order: int = eqx.field(static=True)

    def __init__(self, c, b, velocity, force, constraint_force, constraint_weights, order):
        self.c = _coefficients(c, 1, "c")
        self.b = _coefficients(b, 1, "b")
        self.velocity = _coefficients(velocity, 2, "velocity")
        self.force = _coefficients(force, 2, "force")
        self.constraint_force = _coefficients(constraint_force, 2, "constraint_force")
        self.constraint_weights = _coefficients(constraint_weights, 2, "constraint_weights")
        self.order = int(order)

    def __check_init__(self):
        s = len(self.b)
        if s < 2 or len(self.c) != s:
            raise ValueError(
                f"SPARKTableau needs s >= 2 stages and len(c) == len(b) == s, got c={self.c}, "
                f"b={self.b}."
            )
        for name in ("velocity", "force", "constraint_force"):
            shape = np.shape(getattr(self, name))
            if shape != (s, s):
                raise ValueError(f"SPARKTableau.{name} must have shape ({s}, {s}), got {shape}.")
        # s multipliers per constraint need s constraint equations: s - 1 at the
        # stages and g(q1, p1) = 0 at the end.
        if np.shape(self.constraint_weights) != (s - 1, s):
            raise ValueError(
                f"SPARKTableau.constraint_weights must have shape ({s - 1}, {s}) (s - 1 stage "
                f"constraint equations), got {np.shape(self.constraint_weights)}."
            )
        if not np.isclose(sum(self.b), 1.0, rtol=0.0, atol=1e-12):
            raise ValueError(f"SPARKTableau.b must sum to 1 (consistency), got {self.b}.")
        if self.order < 1:
            raise ValueError(f"SPARKTableau.order must be a positive int, got {self.order}.")

    @property
    def stages(self) -> int:
        return len(self.b)

    def stage_unknowns(self, *names: str) -> tuple[tuple[int, ...], tuple[int, ...]]:
        r"""Which stages of one variable are unknowns of a step, for the variable whose
        stage equations have the tableaux `names` (`"velocity"` for $Q$; `"force"` and
        `"constraint_force"` for $P$). A stage whose rows are zero in all of them is
        the step's start ($Q_1 = q_0$ with Lobatto IIIA, whose first row is zero), and
        one whose rows equal an earlier stage's is that stage ($P_1 = P_2$ with IIIB for
        every force at $s = 2$, whose two rows are $(\tfrac12, 0)$); neither needs an
        unknown or an equation. Rows are compared exactly: the tableaux are static.

        Returns `(rows, source)`: the stages that are unknowns, in order, and for each
        stage the index in `rows` of the stage it equals, or $-1$ for the start."""
        table = np.concatenate([np.asarray(getattr(self, name)) for name in names], axis=1)
        rows, source = [], []
        for i, row in enumerate(table):
            earlier = [j for j, stage in enumerate(rows) if np.array_equal(table[stage], row)]
            if not np.any(row):
                source.append(-1)
            elif earlier:
                source.append(earlier[0])
            else:
                source.append(len(rows))
                rows.append(i)
        return tuple(rows), tuple(source)

    def is_symmetric(self) -> bool:
        r"""Whether the method is self-adjoint (Hairer, Lubich & Wanner, *Geometric
        Numerical Integration*, §V.2): $b_{s+1-j} = b_j$, $c_{s+1-i} = 1 - c_i$, each of
        the three tableaux satisfies $a_{s+1-i,\,s+1-j} + a_{ij} = b_j$, and the stage
        constraint equations are the same set with the stages reversed (the rows of
        $\omega$ reversed span what the rows of $\omega$ span). To $10^{-12}$."""
        b, c = np.asarray(self.b), np.asarray(self.c)
        close = lambda x, y: bool(np.allclose(x, y, rtol=0.0, atol=1e-12))  # noqa: E731
        tableaux = [np.asarray(getattr(self, name)) for name in ("velocity", "force", "constraint_force")]
        weights = np.asarray(self.constraint_weights)
        reversed_weights = np.concatenate([weights, weights[:, ::-1]])
        rank = lambda matrix: np.linalg.matrix_rank(matrix, tol=1e-10)  # noqa: E731
        return (
            close(b, b[::-1])
            and close(c, 1 - c[::-1])
            and all(close(a + a[::-1, ::-1], np.broadcast_to(b, a.shape)) for a in tableaux)
            and rank(reversed_weights) == rank(weights)
        )


def lobatto_coefficients(s: int) -> dict[str, np.ndarray]:
    r"""The $s$-stage Lobatto coefficients on $[0, 1]$ in float64 (Hairer & Wanner,
    *Solving ODEs II*, §IV.5):

    - `c`: $0$, the zeros of $P'_{s-1}(2t - 1)$, $1$; `b`: the Lobatto weights;
    - `IIIA`: collocation, $\sum_j a_{ij}c_j^{k-1} = c_i^k/k$, $k = 1, \dots, s$;
    - `IIIB`: $\hat a_{ij} = b_j(1 - a_{ji}/b_i)$ (so that IIIA-IIIB is symplectic);
    - `IIIC`: $a_{i1} = b_1$ and $\sum_j a_{ij}c_j^{k-1} = c_i^k/k$, $k < s$;
    - `IIIC*`: $a_{is} = 0$ and the same $s - 1$ conditions;
    - `IIID`: $(\mathrm{IIIC} + \mathrm{IIIC^*})/2$.

    IIIA, IIIB and IIID are self-adjoint ($a_{ij} + a_{s+1-i,\,s+1-j} = b_j$); IIIC and
    IIIC* are each other's adjoints.
    """
    if not isinstance(s, int) or s < 2:
        raise ValueError(f"Lobatto methods need an int s >= 2 stages, got {s!r}.")
    interior = np.polynomial.legendre.Legendre.basis(s - 1).deriv().roots() if s > 2 else np.zeros(0)
    c = np.concatenate([[0.0], np.sort((1 + np.real(interior)) / 2), [1.0]])
    powers = np.arange(1, s + 1)
    vandermonde = c[None, :] ** (powers[:, None] - 1)  # [k, j] = c_j^(k-1)
    b = np.linalg.solve(vandermonde, 1.0 / powers)
    integrals = c[:, None] ** powers[None, :] / powers[None, :]  # [i, k] = c_i^k / k
    iiia = np.linalg.solve(vandermonde, integrals.T).T
    iiib = b[None, :] * (1 - iiia.T / b[:, None])

    def simplifying(fixed_column: int, fixed_value: float) -> np.ndarray:
        free = [j for j in range(s) if j != fixed_column]
        system = vandermonde[: s - 1][:, free]  # conditions k = 1 .. s-1
        rhs = integrals[:, : s - 1] - fixed_value * vandermonde[: s - 1, fixed_column][None, :]
        matrix = np.zeros((s, s))
        matrix[:, fixed_column] = fixed_value
        matrix[:, free] = np.linalg.solve(system, rhs.T).T
        return matrix

    iiic = simplifying(0, b[0])
    iiic_star = simplifying(s - 1, 0.0)
    # The solves round: restore the exact structure the method's symmetry rests on.
    b = (b + b[::-1]) / 2
    reverse = lambda matrix: matrix[::-1, ::-1]  # noqa: E731
    iiia = (iiia + b[None, :] - reverse(iiia)) / 2
    iiib = (iiib + b[None, :] - reverse(iiib)) / 2
    iiia[0], iiib[:, -1] = 0.0, 0.0
    return {
        "c": c,
        "b": b,
        "IIIA": iiia,
        "IIIB": iiib,
        "IIIC": iiic,
        "IIIC*": iiic_star,
        "IIID": (iiic + iiic_star) / 2,
    }


def lobatto_constraint_weights(b, c) -> np.ndarray:
    r"""$\omega_{ij} = b_j c_j^{i-1}$, $i = 1, \dots, s - 1$: the stage constraint
    equations say that the Lobatto quadrature of $t^{i-1} g(t)$ vanishes, i.e. that the
    polynomial interpolating $g(Q_j, P_j)$ at the nodes is orthogonal to all polynomials
    of degree $\le s - 2$ on $[0, 1]$ (the quadrature is exact for these products). That
    set of equations is unchanged by $t \mapsto 1 - t$, which the method's symmetry
    needs. For $s = 2$: $(g(Y_1) + g(Y_2))/2 = 0$.

    **The same equations as the IIIA form.** Jay's SPARK methods for index-2 problems
    (Jay 2003, BIT 43:93) are also written, for instance in Verdier's `odelab`, with the
    stage constraints $\sum_j a_{ij}\,g(Y_j) = 0$, $i = 2, \dots, s$, $a$ = Lobatto
    IIIA. Both forms say something about the polynomial $p$ of degree $s - 1$ through
    the $s$ values $g(Y_j)$. With $P(t) = \int_0^t p$, the IIIA form says $P(c_i) = 0$
    at every node, so $P \propto t(1 - t)P'_{s-1}(2t - 1)$, whose zeros are the Lobatto
    nodes. By Legendre's equation $p = P' \propto P_{s-1}(2t - 1)$. That is exactly the
    polynomial of degree $s - 1$ orthogonal to every polynomial of degree $\le s - 2$,
    which is what these weights say. The solution sets are the same, so the two sets of
    rows span the same space (tested for $s = 2, \dots, 5$)."""
    b, c = np.asarray(b, dtype=float), np.asarray(c, dtype=float)
    return b[None, :] * c[None, :] ** np.arange(len(b) - 1)[:, None]


_CONSTRAINT_FORCE_TABLEAUX = ("IIID", "IIIB")


def lobatto_spark_tableau(s: int = 2, constraint_force: str = "IIID") -> SPARKTableau:
    r"""The $s$-stage Lobatto SPARK tableau: velocity with IIIA, $-\partial_q H$ with
    IIIB, the constraint force with `constraint_force`:

    - `"IIID"` (default): Lobatto IIIA-B-C-C*-D, Jay's method; order $2s - 2$;
    - `"IIIB"`: the constraint force treated like the other forces (IIIA-IIIB); for
        $s = 2$ the nonholonomic RATTLE. Order $2s - 2$ as well.

    Both choices are self-adjoint, so the method is time-symmetric. The stage
    constraint equations are `lobatto_constraint_weights`."""
    if constraint_force not in _CONSTRAINT_FORCE_TABLEAUX:
        raise ValueError(
            f"constraint_force must be one of {_CONSTRAINT_FORCE_TABLEAUX}, got {constraint_force!r}."
        )
    coefficients = lobatto_coefficients(s)
    return SPARKTableau(
        c=coefficients["c"],
        b=coefficients["b"],
        velocity=coefficients["IIIA"],
        force=coefficients["IIIB"],
        constraint_force=coefficients[constraint_force],
        constraint_weights=lobatto_constraint_weights(coefficients["b"], coefficients["c"]),
        order=2 * s - 2,
    )


# The default of `nhjax.SPARK`, s = 2, exact: IIIA [[0, 0], [1/2, 1/2]] for the velocity,
# IIIB [[1/2, 0], [1/2, 0]] for every force, the constraint force included (see `SPARK`).
LOBATTO_IIIA_B_2 = SPARKTableau(
    c=(0.0, 1.0),
    b=(0.5, 0.5),
    velocity=((0.0, 0.0), (0.5, 0.5)),
    force=((0.5, 0.0), (0.5, 0.0)),
    constraint_force=((0.5, 0.0), (0.5, 0.0)),
    constraint_weights=((0.5, 0.5),),
    order=2,
)

# Jay's coefficients for s = 2, exact: IIIA [[0, 0], [1/2, 1/2]], IIIB [[1/2, 0], [1/2, 0]],
# IIID = (IIIC + IIIC*)/2 = ([[1/2, -1/2], [1/2, 1/2]] + [[0, 0], [1, 0]])/2.
LOBATTO_IIIA_B_C_CSTAR_D_2 = SPARKTableau(
    c=(0.0, 1.0),
    b=(0.5, 0.5),
    velocity=((0.0, 0.0), (0.5, 0.5)),
    force=((0.5, 0.0), (0.5, 0.0)),
    constraint_force=((0.25, -0.25), (0.75, 0.25)),
    constraint_weights=((0.5, 0.5),),
    order=2,
)
