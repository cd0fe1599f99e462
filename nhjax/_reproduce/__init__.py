"""The paper's numerical experiments (§4: Figures 1 to 3) and two beyond it, a
work-precision diagram (Figure 4) and the contact oscillator in a reversible and a
non-reversible form (Figure 5), computed, plotted, checked against the paper's claims
and written up: `reproduce`, behind `nhjax reproduce`.

Each experiment is one module, `figN.py`, whose `FIGURE` (`_figure.Figure`) holds
everything about it: how it runs, its sizes, its title and its table in the report.
Adding one is that module and its name in `FIGURES`.

Each experiment writes `figN.png` into the output folder; `results.json` holds the
numbers behind them, each experiment's checks (what was measured and the criterion it
was held to), its `status` ("agrees", "partly" or "disagrees", from the checks alone,
see `_common.verdict`), `agrees` and one-line `verdict`, and its wall time; `report.md`
shows it all. Long runs (Figure 1's ensemble, Figure 3's 500 000 steps) go through
`run_chunked` with their chunks under `out/chunks/`, so an interrupted reproduction
continues where it stopped when run again into the same folder.
"""

import importlib
import json
import pathlib
import platform
import time
from collections.abc import Iterable
from typing import Any


# The experiments by name, each the module of that name, imported when it runs (the
# figure modules load matplotlib).
FIGURES = ("fig1", "fig2", "fig3", "fig4", "fig5")


def figure(name: str):
    """The record (`_figure.Figure`) of the experiment `name`."""
    return importlib.import_module(f".{name}", __name__).FIGURE


def _requested(figures: str | Iterable[str]) -> list[str]:
    """The figures asked for, in order, without repeats; "all" means every one."""
    names = [figures] if isinstance(figures, str) else list(figures)
    unknown = [name for name in names if name not in FIGURES + ("all",)]
    if unknown or not names:
        raise ValueError(
            f"Unknown figure(s) {', '.join(map(repr, unknown)) or '(none given)'}: choose from "
            f"{', '.join(FIGURES)} or all."
        )
    if "all" in names:
        return list(FIGURES)
    return [name for name in FIGURES if name in names]


def reproduce(
    figures: str | Iterable[str],
    *,
    quick: bool,
    out: str | pathlib.Path,
    progress: bool = True,
    _sizes: dict[str, Any] | None = None,
) -> dict:
    """Compute the requested experiments and write their figures, `results.json` and
    `report.md` into `out` (created if missing).

    **Arguments:**

    - `figures`: names from `FIGURES`, or `"all"`.
    - `quick`: each figure's quick sizes (Figure 1's ensemble 200 states to t = 500,
        Figure 3's run 50 000 steps, Figure 5's 20 000), a few minutes in all; otherwise
        the paper's sizes.
    - `out`: the output folder. Chunks of long runs go to `out/chunks/`, and a rerun into
        the same folder continues from them.
    - `progress`: progress bars on the long stages.

    Turns on float64 for the process (`jax_enable_x64`): the experiments are about
    errors at roundoff. Returns the contents of `results.json`.
    """
    names = _requested(figures)
    import jax

    jax.config.update("jax_enable_x64", True)
    from . import report
    from ._common import Context

    records = [figure(name) for name in names]
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    shared = {}

    start = time.perf_counter()
    results = {}
    for record in records:
        sizes = (_sizes or {}).get(record.name, record.quick if quick else record.full)
        context = Context(out=out, sizes=sizes, progress=bool(progress), shared=shared)
        began = time.perf_counter()
        results[record.name] = record.run(context)
        results[record.name]["wall_time_s"] = time.perf_counter() - began
    results["meta"] = dict(
        quick=bool(quick),
        figures=names,
        wall_time_s=time.perf_counter() - start,
        jax=jax.__version__,
        backend=jax.default_backend(),
        machine=platform.machine(),
        all_agree=all(results[name]["agrees"] for name in names),
    )
    (out / "results.json").write_text(json.dumps(results, indent=2))
    report.write(out / "report.md", results, records)
    return results
