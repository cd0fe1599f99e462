"""One record of everything about an experiment, which each `figN.py` holds as `FIGURE`:
what `reproduce` runs, at which sizes, and how `report.md` shows it."""

import dataclasses
from collections.abc import Callable
from typing import Any


@dataclasses.dataclass(frozen=True)
class Figure:
    """An experiment of the reproduction.

    - `name`: its name on the command line and of its files (`fig1` writes `fig1.png`).
    - `title`: the report's heading for it.
    - `run(context) -> dict`: computes, plots and checks it (`_common.Context`, whose
      `sizes` are this figure's); the dict holds `settings`, `methods` (a row per
      method), `images`, `checks` and the verdict (`_common.verdict`), and optionally a
      `size_note` on what a reduced size changes.
    - `full`, `quick`: its sizes at the paper's size and at the quick one, instances of
      the figure's own frozen dataclass (so a test can `dataclasses.replace` them).
    - `columns`: the entries of each method's row that the report's table shows.
    - `note`: what the table's numbers are, under it.
    - `more_report(result) -> lines`: more of the report after the note, if any.
    """

    name: str
    title: str
    run: Callable[[Any], dict]
    full: Any
    quick: Any
    columns: tuple[str, ...]
    note: str
    more_report: Callable[[dict], list[str]] | None = None
