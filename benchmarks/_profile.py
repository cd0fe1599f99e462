"""Where a root-find step's time goes: each part of one step of an nhjax method, timed
alone inside a compiled loop (so that dispatch overhead does not count), beside the
measured cost of whole steps."""

import re
import time

import jax
import jax.lax as lax
import jax.numpy as jnp

from nhjax._solver.base import AbstractMethod
from nhjax._solver.chord import chord_inverse


def per_call_us(function, x, repeats: int = 200) -> float:
    """µs per call of `function(x)`, from a `lax.scan` of `repeats` calls; each call's
    input depends on the previous output, so the compiler can neither hoist nor drop it."""

    @jax.jit
    def loop(offset):
        def body(offset, _):
            out = function(x + offset)
            total = sum(jnp.sum(leaf) for leaf in jax.tree.leaves(out))
            return offset + 1e-300 * total, None

        return lax.scan(body, offset, None, length=repeats)[0]

    zero = jnp.zeros((), x.dtype)
    jax.block_until_ready(loop(zero))
    start = time.perf_counter()
    jax.block_until_ready(loop(zero))
    return (time.perf_counter() - start) / repeats * 1e6


def step_parts(system, method, y0, h, iterations: float, args=None, repeats: int = 200) -> dict:
    """µs of each part of one step of `method` (an `nhjax.AbstractMethod`) from `y0`:
    `setup` (state to unknowns, predictor), `chord_matrix` (the method's Jacobian of the
    simplified residual at the guess, and its inverse, as the method forms them
    (`AbstractMethod.chord_matrix`): once per step), `residual` (once
    per root-finder iteration) and `complete` (unknowns to the new state). `model` is
    setup + chord_matrix + iterations x residual + complete. For a method with its own
    `chord_jacobian`, `chord_matrix_by_jacfwd` is the generic `jax.jacfwd` it replaces."""
    carry = method.initial_carry(system, y0, args)
    guess, data = method.setup(system, 0.0, h, y0, args, carry)
    q_or_x = jax.tree.leaves(y0)[0]

    def setup(offset):
        shifted = jax.tree.map(lambda leaf: leaf + offset[0], y0)
        return method.setup(system, 0.0, h, shifted, args, carry)[0]

    parts = dict(
        setup=per_call_us(setup, jnp.zeros((1,), q_or_x.dtype), repeats),
        chord_matrix=per_call_us(lambda u: method.chord_matrix(u, data), guess, repeats),
        residual=per_call_us(lambda u: method.residual(u, data), guess, repeats),
        complete=per_call_us(lambda u: jax.tree.leaves(method.complete(u, data)[0]), guess, repeats),
    )
    if type(method).chord_jacobian is not AbstractMethod.chord_jacobian:
        # The method's own chord Jacobian against the generic one it replaces.
        parts["chord_matrix_by_jacfwd"] = per_call_us(
            lambda u: chord_inverse(jax.jacfwd(method.simplified_residual)(u, data)), guess, repeats
        )
    parts["model"] = (
        parts["setup"] + parts["chord_matrix"] + iterations * parts["residual"] + parts["complete"]
    )
    return parts


def _derivative_programs(system, method, y0, dt, steps: int, loss_of, args=None):
    """The whole-run programs that `derivative_parts` times and `derivative_program_sizes`
    measures, each a jitted function of the start: `{name: function}`, and the recorded
    roots and whether each step succeeded."""
    import nhjax as nh
    from nhjax import _replay

    dt = jnp.asarray(dt)
    t0 = jnp.zeros_like(dt)

    def forward(y):
        return loss_of(nh.integrate(system, method, y, dt, steps, args=args, save_every=steps).ys)

    def record(y):
        return _replay._record(system, method, y, dt, t0, args, steps, steps)[:2]

    # A program of its own, so that the compilation of `functions["record"]` is not
    # found done already.
    roots, succeeded = jax.jit(lambda y: record(y))(y0)

    def replay(y):
        ys, _ = _replay._replayed_saves(system, method, y, dt, t0, args, roots, succeeded, steps, save_every=steps)
        return loss_of(ys)

    functions = dict(forward=jax.jit(forward), record=jax.jit(record), replay=jax.jit(replay),
                     replay_reverse=jax.jit(jax.grad(replay)))
    return functions, roots


def derivative_parts(system, method, y0, dt, steps: int, repeats: int, loss_of, args=None) -> dict:
    """Where the time of a run's reverse-mode derivative goes (`nhjax._replay`), µs per
    step, timed in turns in one process: the forward run (`forward`), the recording
    scan that keeps each step's root (`record`), the replay of the steps from those
    roots without derivatives (`replay`) and with reverse mode through it
    (`replay_reverse`), which is what the derivative adds to the recording; and, per
    call inside a compiled loop at the first step's root, the step's residual
    (`residual`), its Jacobian in the unknowns by `jax.jacfwd` (`jacobian`), and the
    first step replayed from its root with one tangent of the start
    (`step_derivative`: the linearisation at the root that the derivative forms at
    every step, its Jacobian in the unknowns and along the step's data,
    `nhjax._solver.base._linearised`). `loss_of` maps the saved states to the scalar
    that is differentiated."""
    from _timing import run_and_time_interleaved

    functions, roots = _derivative_programs(system, method, y0, dt, steps, loss_of, args)
    _, times = run_and_time_interleaved(functions, y0, repeats=repeats)
    parts = {name: seconds / steps * 1e6 for name, seconds in times.items()}

    t0 = jnp.zeros_like(jnp.asarray(dt))
    carry = method.initial_carry(system, y0, args)
    _, data = method.setup(system, t0, dt, y0, args, carry)
    ones = jax.tree.map(jnp.ones_like, y0)

    def step_derivative(root):
        return jax.jvp(lambda y: method.replay_step(system, t0, dt, y, args, carry, root)[0], (y0,), (ones,))[1]

    parts.update(
        residual=per_call_us(lambda u: method.residual(u, data), roots[0]),
        jacobian=per_call_us(lambda u: jax.jacfwd(method.residual)(u, data), roots[0]),
        step_derivative=per_call_us(step_derivative, roots[0]),
    )
    return parts


def derivative_program_sizes(system, method, y0, dt, steps: int, loss_of, args=None) -> dict:
    """Where the compilation of a run's reverse-mode derivative goes: for each program
    of `derivative_parts` (`forward`, `record`, `replay`, `replay_reverse`; the
    derivative compiles the recording and the reversed replay), its size
    (`hlo_counts`) and the seconds XLA took to compile it (`compile_s`, after its
    tracing and lowering); for `replay_reverse`, also its instructions by where they
    come from (`derivative_contexts`)."""
    functions, _ = _derivative_programs(system, method, y0, dt, steps, loss_of, args)
    sizes = {}
    for name, function in functions.items():
        lowered = function.lower(y0)
        start = time.perf_counter()
        compiled = lowered.compile()
        sizes[name] = dict(compile_s=time.perf_counter() - start, **hlo_counts(compiled))
        if name == "replay_reverse":
            sizes[name]["contexts"] = derivative_contexts(compiled)
    return sizes


# Operations that do no work at run time: they name, pass on or reinterpret buffers.
_FREE_OPERATIONS = {"parameter", "constant", "get-tuple-element", "tuple", "bitcast"}


def _computations(text: str):
    """Each computation of a compiled program's optimised HLO text: `(its name, the rest
    of its header, its lines)`."""
    name, header, lines = None, None, []
    for line in text.splitlines():
        match = re.match(r"^(?:ENTRY )?%?([\w.\-]+) (.*)\{$", line)
        if match:
            if name is not None:
                yield name, header, lines
            name, header, lines = match.group(1), match.group(2), []
        elif name is not None and line.strip() not in ("", "}"):
            lines.append(line)
    if name is not None:
        yield name, header, lines


def _instructions(text: str):
    """Each instruction of a compiled program's optimised HLO text, fused ones included:
    `(its computation, its opcode, its line)`."""
    for computation, _, lines in _computations(text):
        for line in lines:
            instruction = re.match(r"^\s*(?:ROOT )?%?[\w.\-]+ = \S+ ([\w\-]+)\(", line)
            if instruction is not None:
                yield computation, instruction.group(1), line


def hlo_counts(compiled) -> dict:
    """The size of a compiled program (`jax.jit(f).lower(x).compile()`):
    `hlo_instructions`, every instruction of its optimised HLO, fused ones included;
    `operations`, those outside fused computations, less the ones that do no work
    (parameters, constants, tuples and their elements, bitcasts): each of these is one
    kernel or library call when the program runs, and on XLA:CPU the cost of a small
    step is about their number; and `distinct_fusions`, the fused computations that
    differ in more than their names (`_fused_kernels`).

    XLA:CPU emits one kernel for fused computations that are the same but for their
    names, so a computation repeated in a program (a function evaluated in two loops)
    adds instructions but not kernels to compile, and `distinct_fusions` follows the
    compile time where `hlo_instructions` overstates it: Euler's disk's GONZALEZ-R run
    (`nhjax.examples.rolling_disk_3d`, 2 000 steps) with its chord matrix formed in
    the iteration's own loop, one copy of the residual where the program holds two
    (a trial, not kept), had 16 % fewer instructions but 5 % fewer distinct fusions
    (378 to 358), and compiled hardly faster (`derivative_program_sizes` times the
    compilation of such programs)."""
    text = compiled.as_text()
    fused = set(re.findall(r"\bfusion\(.*?calls=%?([\w.\-]+)", text))
    counts = dict(hlo_instructions=0, operations=0)
    for computation, opcode, _ in _instructions(text):
        counts["hlo_instructions"] += 1
        if computation not in fused and opcode not in _FREE_OPERATIONS:
            counts["operations"] += 1
    counts["distinct_fusions"] = len(set(_fused_kernels(text, fused)))
    return counts


def _fused_kernels(text: str, fused: set[str]) -> list[str]:
    """Each fused computation of a compiled program's HLO text (`fused`, their names),
    with the names of its instructions and parameters and its metadata taken out: two
    are equal where XLA emits one kernel for both."""

    def unnamed(line):
        line = re.sub(r", metadata=\{.*?\}(?=,|$)", "", line)
        return re.sub(r"%?[A-Za-z_][\w\-]*(\.\d+)+|%[\w.\-]+", "v", line).strip()

    return [
        "\n".join(map(unnamed, [header, *lines]))
        for name, header, lines in _computations(text)
        if name in fused
    ]


def derivative_contexts(compiled) -> dict:
    """The instructions of a compiled reverse-mode program (all of them, fused ones
    included, as `hlo_counts` counts `hlo_instructions`) by where the transformations
    that JAX records in each one's `op_name` say it comes from:
    `vmapped_transposes` (above all the rows of each step's Jacobian,
    `nhjax._solver.base._linearised`'s batched pullback, but also a step's own
    gradients taken at several points at once, such as the velocities of
    `nhjax._reduced.momentum_by_projection`); `transposed`, the backward sweep's other
    transposes; `rematerialised`, what the backward sweep recomputes
    under `jax.checkpoint` (the replayed step and its linearisation); `forward`, the
    rest (the forward sweeps and what surrounds the loops); and apart, `no_work`, the
    instructions that only name or pass on buffers (most of them the parameters of
    fused computations, which carry no `op_name`)."""
    contexts = dict(vmapped_transposes=0, transposed=0, rematerialised=0, forward=0, no_work=0)
    for _, opcode, line in _instructions(compiled.as_text()):
        name = re.search(r'op_name="([^"]*)"', line)
        name = name.group(1) if name else ""
        if opcode in _FREE_OPERATIONS:
            contexts["no_work"] += 1
        elif "vmap(transpose(" in name:
            contexts["vmapped_transposes"] += 1
        elif "rematted_computation" in name:
            contexts["rematerialised"] += 1
        elif "transpose(" in name:
            contexts["transposed"] += 1
        else:
            contexts["forward"] += 1
    return contexts


def gonzalez_r_pieces(system, method, y0, h, args=None, unknowns=None) -> tuple[dict, dict]:
    r"""The pieces of one GONZALEZ-R step (`nhjax.GonzalezR`) from `y0`, each a function of
    one array at `unknowns` $u$ (default: the first step's root), with
    $\zeta' = \zeta + Su$, $\bar\zeta$ their midpoint, $\bar q$ its position:
    `({name: function}, {name: argument})`.

    - `frame`: $X(\bar q)^Tp$, the QR of $A(\bar q)^T$ and one product with the frame;
    - `frame_derivative`: $Jv$ and $J^Tw$, $J = \partial_q(X^Tp)$ at $\bar q$, by one
      linearisation of the factorisation at $\bar q$ composed with that of $X^Tp$ in
      its reflectors, applied forward and transposed
      (`nhjax._reduced.ReducedSystem.linearised_frame`, as `at` forms them);
    - `field`: the residual with the midpoint gradient alone (no Gonzalez correction),
      $u - h\,\Pi(\bar\zeta)\nabla\mathcal{H}(\bar\zeta)/S$;
    - `correction`: what the Gonzalez correction adds to it, given the midpoint
      gradient: $\mathcal{H}(\zeta')$ and the corrected gradient, values only, as the
      root finder evaluates it (`"rarely"`);
    - `correction_near`: the same at points $10^{-9}$ apart, where the difference of
      the energies comes from the segment's quadrature;
    - `taylor_derivative`: a tangent of the correction there, differentiable
      (`"cond"`), which takes the derivatives of its Taylor form (third derivatives of
      $\mathcal{H}$), as a derivative through such a step does;
    - `residual`: one root-finder residual (`root_find_residual`);
    - `chord_matrix`: the chord matrix and its inverse (`chord_matrix`);
    - `residual_jacobian`: the Jacobian of the residual in the unknowns by `jax.jacfwd`,
      which a derivative of the run forms at every step (`nhjax._solver.base._implicit_root`);
    - `setup` and `complete`: the state to the unknowns and predictor, the unknowns to
      the new state.

    `correction` returns the corrected gradient $g$, so that $u - h\,\Pi(\bar\zeta)g/S$
    is the residual at $u$ (`tests/test_benchmarks.py`)."""
    from nhjax import _replay
    from nhjax._discrete_gradient import gonzalez_correction

    dt = jnp.asarray(h)
    root = unknowns
    if root is None:
        root = _replay._record(system, method, y0, dt, jnp.zeros_like(dt), args, 1, 1)[0][0]
    carry = method.initial_carry(system, y0, args)
    _, data = method.setup(system, 0.0, dt, y0, args, carry)
    reduced, zeta, scale = data.reduced, data.zeta, data.scale
    zeta1 = zeta + scale * root
    midpoint = 0.5 * (zeta + zeta1)
    n = y0[0].shape[0]
    at_midpoint = reduced.at(midpoint, args)
    momentum, gradient = at_midpoint.momentum, at_midpoint.gradient

    def frame(q):
        return reduced.frame(q, args).transpose_times(momentum)

    def frame_derivative(q):
        _, contracted_products = reduced.linearised_frame(q, args)
        times, transpose_times = contracted_products(momentum)
        # J^T applied to the gradient's rho part, as `at` applies it.
        return times(q), transpose_times(gradient[n:])

    def correction(end, branch="rarely"):
        energy1, segment = reduced.energy_segment(zeta, data.momentum, end, args)
        return gonzalez_correction(
            reduced.hamiltonian, gradient, zeta, end, args,
            branch=branch, taylor=True, f_x=data.energy, f_x1=energy1, segment=segment,
        )

    def setup(offset):
        shifted = jax.tree.map(lambda leaf: leaf + offset[0], y0)
        return method.setup(system, 0.0, dt, shifted, args, carry)[0]

    near = zeta + 1e-9 * scale * root / jnp.max(jnp.abs(root))
    pieces = dict(
        frame=(frame, midpoint[:n]),
        frame_derivative=(frame_derivative, midpoint[:n]),
        field=(lambda u: method.simplified_residual(u, data), root),
        correction=(correction, zeta1),
        correction_near=(correction, near),
        taylor_derivative=(lambda end: jax.jvp(lambda e: correction(e, "cond"), (end,), (root,))[1], near),
        residual=(lambda u: method.root_find_residual(u, data), root),
        chord_matrix=(lambda u: method.chord_matrix(u, data), root),
        residual_jacobian=(lambda u: jax.jacfwd(method.residual)(u, data), root),
        setup=(setup, jnp.zeros((1,), root.dtype)),
        complete=(lambda u: jax.tree.leaves(method.complete(u, data)[0]), root),
    )
    return {name: f for name, (f, _) in pieces.items()}, {name: x for name, (_, x) in pieces.items()}


def gonzalez_r_parts(system, method, y0, h, args=None, repeats: int = 200, budget_s: float = 2.0) -> dict:
    """µs per call (`per_call_us`) and program size (`hlo_counts`) of each piece of a
    GONZALEZ-R step (`gonzalez_r_pieces`), from a loop of `repeats` calls, or fewer
    (at least five) where one call of the compiled piece takes more than
    `budget_s / repeats` (the Jacobians of large systems)."""
    functions, arguments = gonzalez_r_pieces(system, method, y0, h, args)
    parts = {}
    for name, function in functions.items():
        compiled = jax.jit(function).lower(arguments[name]).compile()
        start = time.perf_counter()
        jax.block_until_ready(compiled(arguments[name]))
        calls = min(repeats, max(5, int(budget_s / (time.perf_counter() - start))))
        parts[name] = dict(us=per_call_us(function, arguments[name], calls), **hlo_counts(compiled))
    return parts
