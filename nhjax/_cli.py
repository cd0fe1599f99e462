"""The `nhjax` command."""

import argparse
import math
import os
import pathlib
import shutil
import signal
import sys
import tempfile
import textwrap
import threading
import time
import warnings

from ._methods import integrates_adapted, METHODS, takes_either_form
from ._solver import Composition
from ._reproduce import FIGURES
from .examples import EXAMPLES


def _demo(arguments) -> int:
    """Integrate the Chaplygin sleigh of Figure 2 and report what is conserved."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import nhjax as nh

    sleigh = nh.examples.chaplygin_sleigh(J=8.0, a=1.0, m=1.0)
    x0 = sleigh.initial_state(x1=-5.0, x2=0.0, theta=0.1, rho1=0.001, rho2=-0.6)
    start = time.perf_counter()
    solution = nh.integrate(
        sleigh.adapted, nh.DiscreteGradient(), x0, dt=arguments.dt, n_steps=arguments.steps,
        args=sleigh.args, progress=arguments.progress,
    )
    jax.block_until_ready(solution.ys)
    elapsed = time.perf_counter() - start

    discrete = nh.examples.discrete_constraint_residual(sleigh.constraints, solution.ys[:, :3], sleigh.args)

    def canonical_residual(x):
        q, p = sleigh.from_adapted(x)
        return sleigh.constraints(q, sleigh.args) @ jnp.linalg.solve(sleigh.metric(q, sleigh.args), p)

    canonical = jax.vmap(canonical_residual)(solution.ys)
    energy_error = jnp.max(jnp.abs(solution.energy / solution.energy[0] - 1))
    rho_final = solution.ys[-1, 3:]
    print("Chaplygin sleigh (paper §4.2, Figure 2): J = 8, a = m = 1,")
    print(f"  h = {arguments.dt}, {arguments.steps} steps of DiscreteGradient(gonzalez), from rho = (0.001, -0.6)")
    print(f"  max relative energy error          {float(energy_error):.2e}")
    print(f"  max discrete constraint residual   {float(jnp.max(jnp.abs(discrete))):.2e}")
    print(f"  max constraint residual A(q) qdot  {float(jnp.max(jnp.abs(canonical))):.2e}")
    print(f"  final (rho1, rho2) = ({float(rho_final[0]):.3e}, {float(rho_final[1]):.12f})"
          f"  [Proposition 4.1: -> (0, {float(jnp.hypot(0.001, 0.6)):.12f})]")
    print(f"  root-finder iterations per step    {float(solution.stats['root_find_steps']) / arguments.steps:.2f}")
    print(f"  wall time (with compilation)       {elapsed:.2f} s")
    return 0


# The systems the command sets up: every example, each from its usual start.
SYSTEMS = {name: example.title for name, example in EXAMPLES.items()}


def _system_listing() -> dict[str, str]:
    """Each example's line with its forms and the names --start takes."""
    listing = {}
    for name, example in EXAMPLES.items():
        made = example()
        choices = ", ".join(f"{choice} = {default}" for choice, default in made.initial_state_choices().items())
        listing[name] = f"{example.title}; forms: {', '.join(made.forms())}; --start {choices}"
    return listing
_USER_SYSTEM = {
    "MODULE:FACTORY": "your own system (also --system MODULE:FACTORY): FACTORY() in MODULE returns "
    "(system, (q0, p0), args), the system a nhjax.NonholonomicSystem",
}


class _FactoryError(Exception):
    """A user's `MODULE:FACTORY` that cannot be imported or returns the wrong thing."""


def _user_problem(spec: str):
    """(system, (q0, p0), args, a description) from `factory()` of `MODULE:FACTORY`.
    The current folder is searched first for MODULE, as `python -m` does, so that a
    file `./my_system.py` is `my_system:factory`."""
    import importlib

    import nhjax as nh

    module_name, _, factory_name = spec.partition(":")
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    try:
        module = importlib.import_module(module_name)
    except Exception as error:
        raise _FactoryError(f"cannot import module {module_name!r} of {spec}: {type(error).__name__}: {error}") from None
    factory = getattr(module, factory_name, None)
    if not callable(factory):
        raise _FactoryError(f"module {module_name!r} has no function {factory_name!r}")
    try:
        produced = factory()
    except KeyboardInterrupt:
        raise
    except BaseException as error:  # SystemExit included: the factory is not the command
        raise _FactoryError(
            f"{spec}() failed (it is called with no arguments): {type(error).__name__}: {error}"
        ) from None
    expected = "(system, (q0, p0), args), the system a NonholonomicSystem"
    if not (isinstance(produced, tuple) and len(produced) == 3):
        raise _FactoryError(f"{spec}() must return {expected}; it returned {type(produced).__name__}")
    system, y0, args = produced
    if not isinstance(system, nh.NonholonomicSystem):
        raise _FactoryError(f"{spec}() must return {expected}; its system is a {type(system).__name__}")
    try:
        system.check_shapes(y0, args)
    except (TypeError, ValueError) as error:
        raise _FactoryError(f"{spec}() returned an initial state that does not fit its system: {error}") from None
    return system, y0, args, f"{spec}()"


def _form(arguments) -> str:
    """The form of the system the method integrates: "adapted" (the reduced equations)
    or "canonical"; for a method that takes either, canonical where the example has it."""
    solver = METHODS[arguments.method].solver
    if integrates_adapted(solver):
        return "adapted"
    if takes_either_form(solver) and not _is_factory(arguments.system):
        if "canonical" not in EXAMPLES[arguments.system]().forms():
            return "adapted"
    return "canonical"


def _problem(arguments):
    """(system, initial state, args, a description) of the chosen example in the form
    its method integrates, or of the user's factory."""
    import jax

    if _is_factory(arguments.system):
        return _user_problem(arguments.system)
    example = EXAMPLES[arguments.system]()
    form = _form(arguments)
    if arguments.seed is not None:
        state = example.start(form, key=jax.random.key(arguments.seed))
        start = f"random state of seed {arguments.seed}"
    else:
        choices = example.initial_state_choices() | dict(arguments.start)
        state = example.start(form, **dict(arguments.start))
        start = ", ".join(f"{name} = {value}" for name, value in choices.items())
    parameters = ", ".join(f"{name} = {value}" for name, value in example.parameters().items())
    description = f"{example.name} ({parameters})" if parameters else example.name
    return example.system(form), state, example.args, f"{description}, {form} form, from {start}"


# Step counts are int64 in the loop (diffrax's), with room for the count of saves.
_MOST_STEPS = 2**62


def _composed(method, order: int):
    """`method`, or its symmetric composition of `order` (`nhjax.Composition`)."""
    return method if order == 2 else Composition(method, order)


def _method_label(arguments) -> str:
    label = METHODS[arguments.method].name
    return label if arguments.order == 2 else f"{label} composed to order {arguments.order}"


def _simulate(arguments, n_steps: int) -> int:
    """Run one example with one method through `run_chunked`, write the trajectory and
    print what was conserved."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import nhjax as nh
    from ._chunk_files import write_atomically
    from ._runner import run_chunked

    try:
        system, y0, args, description = _problem(arguments)
    except _FactoryError as error:
        print(f"nhjax simulate: error: {error}", file=sys.stderr)
        return 2
    shortfall = _disk_shortfall(_output_path(arguments), system, y0, args, n_steps // arguments.save_every + 1)
    if shortfall:
        print(f"nhjax simulate: error: {shortfall}", file=sys.stderr)
        return 2
    method = _composed(METHODS[arguments.method].solver, arguments.order)  # checked with the arguments
    out = _output_path(arguments)
    chunks = out.with_name(out.name + ".chunks")
    on_disk = len(list(chunks.glob("chunk_*.npz")))
    start = time.perf_counter()
    try:
        solution = run_chunked(
            system, method, y0, arguments.dt, n_steps, directory=chunks, args=args,
            save_every=arguments.save_every, chunk_steps=arguments.chunk_steps,
            progress=arguments.progress,
        )
    except (RuntimeError, ValueError) as error:  # a failed chunk, or a different run in `chunks`
        print(f"nhjax simulate: error: {error}", file=sys.stderr)
        return 1
    except OSError as error:  # a full disk, say, while writing a chunk
        print(
            f"nhjax simulate: error: cannot write the chunks in {chunks}: {error}. The chunks "
            "written so far are kept there; rerun the same command to continue from them.",
            file=sys.stderr,
        )
        return 1
    elapsed = time.perf_counter() - start

    # Canonical runs save (q, p) and the constraint residual; adapted ones their state x,
    # in which the constraint holds by construction.
    states = dict(zip(("q", "p"), solution.ys)) if isinstance(solution.ys, tuple) else dict(x=solution.ys)
    trajectory = dict(ts=solution.ts, **states, energy=solution.energy)
    if solution.constraint is not None:
        trajectory["constraint"] = solution.constraint
    if system.is_forced():  # a conservative run's ledger is zeros: not worth a file
        trajectory.update(work=solution.work, dissipated=solution.dissipated)
    trajectory = {name: np.asarray(values) for name, values in trajectory.items()}
    try:
        write_atomically(out, lambda file: np.savez(file, **trajectory))
    except OSError as error:
        print(
            f"nhjax simulate: error: cannot write {out}: {error}. The run's chunks are kept in "
            f"{chunks}; rerun the same command to write {out} from them.",
            file=sys.stderr,
        )
        return 1
    # The chunks only served to resume; the trajectory is complete in `out` now (a run
    # beside this one that finished first may have removed them already).
    shutil.rmtree(chunks, ignore_errors=True)

    energy = trajectory["energy"]
    scale = abs(energy[0]) if energy[0] != 0 else 1.0  # relative unless H(0) = 0
    print(f"{description}; {_method_label(arguments)}, h = {arguments.dt}, t1 = {arguments.t1}")
    print(f"  steps                              {n_steps}" + (f" (resumed: {on_disk} chunks were on disk)" if on_disk else ""))
    print(f"  saves                              {energy.shape[0]}, written to {out}")
    if "work" in trajectory:
        # A forced system: its energy is not kept but balanced, H - H(0) = W - D.
        work, dissipated = trajectory["work"], trajectory["dissipated"]
        balance = energy - energy[0] - (work - dissipated)
        print(f"  energy supplied, dissipated        {work[-1]:.6g}, {dissipated[-1]:.6g}")
        print(f"  max relative energy balance error  {np.max(np.abs(balance)) / max(scale, np.max(np.abs(energy))):.2e}")
    else:
        print(f"  max relative energy error          {np.max(np.abs(energy - energy[0])) / scale:.2e}")
    if "constraint" in trajectory:
        print(f"  max constraint error |A(q) dH/dp|  {np.max(np.abs(trajectory['constraint'])):.2e}")
    else:
        print("  constraint                         kept by the adapted coordinates")
    print(f"  result                             {nh.RESULTS[solution.result] or 'successful'}")
    print(f"  wall time (with compilation)       {elapsed:.2f} s")
    return 0


def _disk_shortfall(out: pathlib.Path, system, y0, args, saves: int) -> str | None:
    """Why the saves cannot fit on the disk of `out`, or `None`: each save holds t, the
    state, the energy, any constraint residual and the energy ledger (work, dissipated)
    in float64, written twice (the chunks, then the trajectory; an upper bound, as a
    conservative trajectory's file leaves the ledger out)."""
    import jax

    state = sum(leaf.size for leaf in jax.tree.leaves(y0))
    rows = system.constraints(y0[0], args).shape[0] if hasattr(system, "constraints") else 0
    needed = 2 * saves * 8 * (4 + state + rows)
    folder = out.absolute().parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    free = shutil.disk_usage(folder).free
    if needed > free:
        return (
            f"{saves:.3g} saves need about {needed / 2**30:.3g} GiB, and {folder} has {free / 2**30:.3g} "
            "GiB free: save less often (--save-every), or take fewer steps"
        )
    return None


def _output_path(arguments) -> pathlib.Path:
    order = "" if arguments.order == 2 else f"-order{arguments.order}"
    return pathlib.Path(arguments.out or f"{arguments.system.replace(':', '.')}-{arguments.method}{order}.npz")


def _output_problem(out: pathlib.Path) -> str | None:
    """Why `out` and its chunk folder cannot be written, or `None`: checked before any
    work, by creating (and removing) a file in the nearest folder that exists (missing
    folders are created by the run)."""
    chunks = out.with_name(out.name + ".chunks")
    if out.is_dir():
        return f"{out} is a directory; give the name of the .npz file to write"
    if chunks.exists() and not chunks.is_dir():
        return f"{chunks}, where the run keeps its chunks, exists and is not a directory"
    folder = out.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        return f"cannot write {out}: {folder} is not a directory"
    try:
        handle, probe = tempfile.mkstemp(dir=folder, prefix=f".{out.name}.", suffix=".probe")
    except OSError as error:
        return f"cannot write {out}: {error.strerror or error}"
    os.close(handle)
    os.unlink(probe)
    return None


def _reproduce(arguments) -> int:
    # `figures` is the default "all", or the list given (repeats dropped, order kept).
    figures = FIGURES if "all" in arguments.figures else tuple(dict.fromkeys(arguments.figures))
    from ._reproduce import reproduce

    results = reproduce(figures, quick=arguments.quick, out=arguments.out, progress=arguments.progress)
    print(f"Report, figures and results.json in {arguments.out}")
    for name, result in results.items():
        if isinstance(result, dict) and "verdict" in result:
            status = result.get("status", "agrees" if result.get("agrees") else "disagrees")
            agreement = {"agrees": "agrees with the paper", "partly": "agrees with the paper in part"}.get(
                status, "DOES NOT AGREE with the paper"
            )
            print(f"  {name}: {agreement}: {result['verdict']}")
    return 0


def _listing(entries: dict) -> str:
    """Names and their texts in two columns; a name too long for its column stands on a
    line of its own, as argparse sets long options."""
    indent = " " * 14
    return "\n".join(
        textwrap.fill(text, 80, initial_indent=f"  {name:<12}", subsequent_indent=indent)
        if len(name) < 12
        else f"  {name}\n" + textwrap.fill(text, 80, initial_indent=indent, subsequent_indent=indent)
        for name, text in entries.items()
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="nhjax",
        description="Energy- and constraint-preserving integrators for nonholonomic systems.",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser(
        "demo", help="integrate the Chaplygin sleigh and print its energy and constraint errors"
    )
    demo.add_argument("--dt", type=float, default=0.5, help="step size h (default 0.5, as in Figure 2)")
    demo.add_argument("--steps", type=int, default=2000, help="number of steps (default 2000)")
    demo.add_argument("--progress", action="store_true", help="show a progress bar")

    simulate = commands.add_parser(
        "simulate",
        help="integrate one of the paper's systems, or your own, with one method and save the trajectory",
        description=textwrap.fill(
            "Integrate one of the paper's systems or your own (canonical coordinates, float64) with one "
            "method, write the saved trajectory to an .npz file (arrays ts, q, p, energy, "
            "constraint; ts, x, energy for a method on the reduced equations in adapted coordinates) "
            "and print the energy and constraint errors. The run goes in chunks "
            "kept in FILE.chunks/ until FILE is written, so an interrupted run continues "
            "where it stopped when rerun with the same arguments.", 80
        ),
        epilog=f"systems:\n{_listing(_system_listing())}\n{_listing(_USER_SYSTEM)}\n\nmethods:\n"
        + _listing({name: f"{method.name} ({method.description})" for name, method in METHODS.items()}),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    simulate.add_argument(
        "system", nargs="?", metavar="SYSTEM",
        help=f"one of {', '.join(SYSTEMS)}, or MODULE:FACTORY (see below)",
    )
    simulate.add_argument(
        "--system", dest="factory", metavar="MODULE:FACTORY",
        help="your own system: FACTORY() in MODULE returns (system, (q0, p0), args), the system a "
        "nhjax.NonholonomicSystem; MODULE is searched for in the current folder first",
    )
    simulate.add_argument("--method", required=True, choices=METHODS, metavar="METHOD", help=f"one of {', '.join(METHODS)} (see below)")
    simulate.add_argument(
        "--order", type=int, choices=Composition.orders, default=2, metavar="P",
        help="compose the method symmetrically to order P, one of 2 (the method itself), "
        + ", ".join(
            "{} ({}, {} substeps a step)".format(order, *Composition.recommended_scheme(order))
            for order in Composition.orders
            if order != 2
        )
        + "; not with tsit5",
    )
    simulate.add_argument("--dt", type=float, required=True, metavar="H", help="step size h > 0")
    simulate.add_argument("--t1", type=float, required=True, metavar="T", help="final time, a whole number of steps: t1/h steps are taken")
    simulate.add_argument("--save-every", type=int, default=1, metavar="K", help="save every K-th step; K must divide t1/h (default 1)")
    simulate.add_argument("--out", metavar="FILE", help="the .npz file to write (default SYSTEM-METHOD.npz, or SYSTEM-METHOD-orderP.npz)")
    simulate.add_argument(
        "--chunk-steps", type=int, metavar="N",
        help="steps per chunk written to FILE.chunks/, a multiple of K (default about 50 000)",
    )
    simulate.add_argument(
        "--start", type=_start_choice, action="append", default=[], metavar="NAME=VALUE",
        help="start from the example's initial state with NAME = VALUE instead of its default, for "
        "instance --start angle=0.9 for the quartic (repeat for several; each system's names are "
        "listed below)",
    )
    simulate.add_argument(
        "--seed", type=int, metavar="S",
        help=f"a random initial state of this seed ({', '.join(_random_systems())})",
    )
    simulate.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True, help="show a progress bar (default on)")

    reproduce = commands.add_parser(
        "reproduce",
        help="rerun the paper's experiments and write figures, results.json and report.md",
        description="Rerun the experiments behind the paper's figures (and a work-precision "
        "comparison, fig4, and the contact oscillator in a reversible and a non-reversible form, "
        "fig5), write the figures as PNG, the numbers in results.json and a "
        "report.md that says, experiment by experiment, whether the paper's claims hold. "
        "Long runs resume from their chunks in DIR if interrupted.",
    )
    reproduce.add_argument(
        "figures", nargs="*", choices=(*FIGURES, "all"), default="all", metavar="FIGURE",
        help=f"which to reproduce: any of {', '.join(FIGURES)}, or all (default)",
    )
    reproduce.add_argument("--quick", action="store_true", help="smaller runs (minutes, not a quarter of an hour) that still show each claim")
    reproduce.add_argument("--out", type=pathlib.Path, default=pathlib.Path("nhjax-reproduction"), metavar="DIR", help="output folder (default ./nhjax-reproduction)")
    reproduce.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True, help="show progress bars (default on)")

    arguments = parser.parse_args(argv)
    # Ctrl-C leaves from the signal handler itself: a KeyboardInterrupt raised while
    # Python runs a callback (JAX's garbage-collection hook, say) is printed and dropped,
    # and the run would go on. An ignored SIGINT (nohup) stays ignored.
    previous = signal.getsignal(signal.SIGINT)
    handles = threading.current_thread() is threading.main_thread() and previous not in (signal.SIG_IGN, None)
    if handles:
        signal.signal(signal.SIGINT, _leave_on_interrupt)
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            return _run_command(arguments, parser, simulate)
    except KeyboardInterrupt:
        _leave_on_interrupt()
    finally:
        if handles:
            signal.signal(signal.SIGINT, previous)


def _leave_on_interrupt(*_) -> None:
    """Leave at once: unwinding the interpreter while XLA is compiling can crash it.
    Finished chunks are on disk, and a rerun continues from them."""
    print("\nnhjax: interrupted", file=sys.stderr, flush=True)
    sys.stdout.flush()
    os._exit(130)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning (such as a chunk found corrupted and computed again) as one line."""
    del category, filename, lineno, line
    print(f"nhjax: warning: {message}", file=sys.stderr if file is None else file)


def _run_command(arguments, parser, simulate) -> int:
    if arguments.command == "demo":
        if not (math.isfinite(arguments.dt) and arguments.dt > 0):
            parser.error(f"--dt must be positive and finite, got {arguments.dt}")
        if arguments.steps < 1:
            parser.error(f"--steps must be a positive integer, got {arguments.steps}")
        return _demo(arguments)
    if arguments.command == "reproduce":
        return _reproduce(arguments)
    arguments.system = _checked_system(simulate, arguments)
    n_steps = _checked_steps(simulate, arguments)
    problem = _output_problem(_output_path(arguments))
    if problem:
        simulate.error(f"argument --out: {problem}")
    return _simulate(arguments, n_steps)


def _is_factory(system: str) -> bool:
    module, colon, factory = system.partition(":")
    return bool(colon and module and factory)


def _checked_system(parser, arguments) -> str:
    """The system: a built-in example's name or MODULE:FACTORY, given once, either as
    SYSTEM or as --system."""
    if (arguments.system is None) == (arguments.factory is None):
        parser.error("give the system once: SYSTEM, or --system MODULE:FACTORY")
    system = arguments.system or arguments.factory
    if system in SYSTEMS or _is_factory(system):
        return system
    if arguments.factory is not None:
        parser.error(f"argument --system: expected MODULE:FACTORY, got {system!r}")
    parser.error(
        f"argument SYSTEM: invalid choice: {system!r} (choose from {', '.join(map(repr, SYSTEMS))}, "
        "or give MODULE:FACTORY)"
    )


def _checked_steps(parser, arguments) -> int:
    """The number of steps t1/h, after checking the simulate options; argparse errors
    (exit status 2) otherwise."""
    if not (math.isfinite(arguments.dt) and arguments.dt > 0):
        parser.error(f"--dt must be positive and finite, got {arguments.dt}")
    if not (math.isfinite(arguments.t1) and arguments.t1 > 0):
        parser.error(f"--t1 must be positive and finite, got {arguments.t1}")
    n_steps = round(arguments.t1 / arguments.dt)
    if n_steps < 1 or abs(n_steps * arguments.dt - arguments.t1) > 1e-9 * arguments.t1:
        parser.error(
            f"--t1 must be a whole number of steps: t1/h = {arguments.t1 / arguments.dt:g}"
        )
    if n_steps > _MOST_STEPS:
        parser.error(
            f"--t1/--dt asks for {n_steps:.3g} steps, more than the {_MOST_STEPS:.3g} a run can "
            "count (int64); take a larger --dt"
        )
    if arguments.save_every < 1 or n_steps % arguments.save_every:
        parser.error(
            f"--save-every must be a positive divisor of the number of steps t1/h = "
            f"{n_steps}, got {arguments.save_every}"
        )
    if arguments.chunk_steps is not None and (
        arguments.chunk_steps < 1 or arguments.chunk_steps % arguments.save_every
    ):
        parser.error(
            f"--chunk-steps must be a positive multiple of --save-every "
            f"{arguments.save_every}, got {arguments.chunk_steps}"
        )
    if arguments.order != 2:
        # The composition itself says whether it can raise the method's order.
        try:
            _composed(METHODS[arguments.method].solver, arguments.order)
        except ValueError as error:
            parser.error(f"argument --order: {error}")
    _check_start(parser, arguments)
    return n_steps


def _random_systems() -> list[str]:
    return [name for name, example in EXAMPLES.items() if example().has_random_states()]


def _start_choice(text: str) -> tuple[str, int | float]:
    """NAME=VALUE, VALUE an integer where it is written as one (a seed), a float otherwise."""
    name, equals, value = text.partition("=")
    if equals and name:
        for number in (int, float):
            try:
                return name, number(value)
            except ValueError:
                pass
    raise argparse.ArgumentTypeError(f"expected NAME=VALUE with a number VALUE, got {text!r}")


def _check_start(parser, arguments) -> None:
    """--start and --seed against the example (a user's factory gives its own start)."""
    if _is_factory(arguments.system):
        if arguments.start or arguments.seed is not None:
            parser.error("--start and --seed are for the built-in systems; a factory returns its own start")
        if integrates_adapted(METHODS[arguments.method].solver):
            parser.error(
                f"argument --method: {arguments.method} integrates reduced equations in adapted "
                "coordinates (a SkewGradientSystem); a factory's system is a NonholonomicSystem"
            )
        return
    example = EXAMPLES[arguments.system]()
    form = _form(arguments)
    if form not in example.forms():
        parser.error(
            f"argument --method: {arguments.method} integrates the {form} form, and the "
            f"{arguments.system} example comes in {', '.join(example.forms())} form only"
        )
    choices = example.initial_state_choices()
    for name, _ in arguments.start:
        if name not in choices:
            parser.error(
                f"argument --start: the {arguments.system} example's initial state takes "
                f"{', '.join(choices) or 'no names'}, not {name!r}"
            )
    if arguments.seed is not None:
        if not example.has_random_states():
            parser.error(f"--seed needs a system with random initial states ({', '.join(_random_systems())}), not {arguments.system}")
        if arguments.seed < 0:
            parser.error(f"--seed must be a non-negative integer, got {arguments.seed}")
        if arguments.start:
            parser.error("give --start or --seed, not both")


if __name__ == "__main__":
    sys.exit(main())
