"""`report.md`: each experiment's figure, the numbers behind it, its wall time and one
line on whether it agrees with the paper."""

import pathlib

from ._common import METHODS
from ._figure import Figure


def number(value) -> str:
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        return f"{value:.3g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(number(item) for item in value)
    return str(value)


def _table(rows: dict, columns: list[str]) -> list[str]:
    lines = ["| method | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for name, values in rows.items():
        lines.append(f"| {name} | " + " | ".join(number(values.get(column)) for column in columns) + " |")
    return lines


def write(path: pathlib.Path, results: dict, figures: list[Figure]) -> None:
    """`report.md` for the `results` of `figures`, in their order."""
    meta = results["meta"]
    mode = "quick (reduced sizes)" if meta["quick"] else "full (the paper's sizes)"
    lines = [
        "# nhjax: reproduction of Celledoni, Farré Puiggalí, Høiseth, Martín de Diego,",
        "# *Energy-preserving integrators applied to nonholonomic systems*",
        "",
        f"Mode: {mode}. Float64. Total wall time {meta['wall_time_s']:.1f} s, compilation included "
        f"(jax {meta['jax']}, {meta['backend']}).",
        "",
        "| experiment | verdict | wall time (s) |",
        "|---|---|---|",
    ]
    for figure in figures:
        lines.append(f"| {figure.name} | {_status(results[figure.name])} | {results[figure.name]['wall_time_s']:.1f} |")
    used = [method for method in METHODS if any(method in results[figure.name]["methods"] for figure in figures)]
    lines += ["", "Methods: " + "; ".join(f"**{method}**: {METHODS[method].description}" for method in used) + "."]
    for figure in figures:
        result = results[figure.name]
        lines += ["", f"## {figure.title}", ""]
        lines += [f"![{figure.name}]({image})" for image in result["images"]]
        lines += [
            "",
            f"**Agreement with the paper: {_status(result)}.** {result['verdict']}",
            "",
            f"Wall time: {result['wall_time_s']:.1f} s (compilation included).",
            "",
            "Settings: " + "; ".join(f"{key} = {number(value)}" for key, value in result["settings"].items()) + ".",
            "",
        ]
        if result.get("size_note"):
            lines += [f"**Reduced size:** {result['size_note']}", ""]
        lines += _table(result["methods"], list(figure.columns))
        lines += ["", figure.note]
        if figure.more_report is not None:
            lines += ["", *figure.more_report(result)]
    path.write_text("\n".join(lines) + "\n")


def _status(result: dict) -> str:
    """The status shown: agrees, partly, or DISAGREES (loud: the one a reader must not
    miss)."""
    status = result.get("status", "agrees" if result["agrees"] else "disagrees")
    return "DISAGREES" if status == "disagrees" else status
