"""`report.md`: each experiment's figure, the numbers behind it, its wall time and one
line on whether it agrees with the paper."""

import pathlib

from ._common import METHODS


TITLES = {
    "fig1": "Figure 1: the chaotic quartic (§4.1)",
    "fig2": "Figure 2: the Chaplygin sleigh (§4.2)",
    "fig3": "Figure 3: the gearbox driven by an asymmetric pendulum (§4.4)",
    "fig4": "Figure 4 (beyond the paper): work against precision on the chaotic quartic",
    "fig5": "Figure 5 (beyond the paper): reversibility and a second first integral, on the contact oscillator",
}


def _number(value) -> str:
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        return f"{value:.3g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(_number(item) for item in value)
    return str(value)


def _table(rows: dict, columns: list[str]) -> list[str]:
    lines = ["| method | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for name, values in rows.items():
        lines.append(f"| {name} | " + " | ".join(_number(values.get(column)) for column in columns) + " |")
    return lines


_COLUMNS = {
    "fig1": ["fitted_order", "errors_at_t10", "max_constraint_error", "max_relative_energy_error",
             "variance_slope_relative_to_line", "variance_intercept_over_h4", "final_variance_over_h4"],
    "fig2": ["final_rho", "time_rho2_turns_positive", "max_relative_energy_error", "max_constraint_error"],
    "fig3": ["max_relative_energy_error", "final_relative_energy_error", "max_constraint_error"],
    "fig4": ["settings", "wall_time_s", "energy_error", "solution_error", "fitted_order"],
    "fig5": ["max_relative_energy_error", "max_y_energy_error", "y_energy_error_growth"],
}

_NOTES = {
    "fig1": (
        "Errors at t = 10 are max-norm distances in (q, p) from Dopri8 at rtol = atol = 1e-13, "
        "at the step sizes listed in the settings. Panels (b) and (c) follow the ensemble's first "
        "trajectory, which is also the start of (a). The variance slope is fitted with an intercept "
        "over the last 90% of the run and is given in units of 1e-4 h^4 per unit time (1 = on the "
        "paper's line); the intercept is the bounded part, in units of h^4."
    ),
    "fig2": "rho = (rho1, rho2) in the paper's orthonormal frame, for rho1(0) = -0.001 and 0.001.",
    "fig3": "Errors are maxima over the saves (every 100 steps).",
    "fig4": (
        "`settings` are the step sizes (Dopri8: the tolerances rtol = atol). Wall times are medians "
        "after compilation, of one trajectory to t = 10 on this machine. Energy-exact runs: the "
        "discrete-gradient methods, their compositions, and Dopri8 with each step projected onto "
        "the energy level and the constraint. The ratio is the energy-exact run's time "
        "over the cheapest run's."
    ),
    "fig5": (
        "The same motion in two coordinate systems: the reversible adapted form and the gauge-shifted "
        "one (nhjax.examples.contact_oscillator), and the canonical form for the methods that take only it. "
        "H_y = (y^2 + ydot^2)/2 is a first integral of the exact flow; its error growth is the error's "
        "mean over the second half of the run over its mean over the first (1 bounded, 3 a linear drift)."
    ),
}


def _cheapest_table(cheapest: dict) -> list[str]:
    """Figure 4's cheapest runs at each target error, as a table."""

    def run(entry):
        if entry is None:
            return "none reaches it"
        return f"{entry['method']} at {_number(entry['setting'])}: {entry['wall_time_s'] * 1e3:.2f} ms"

    lines = [
        "| error at t = 10 | cheapest run | cheapest energy-exact run | ratio |",
        "|---|---|---|---|",
    ]
    for target, row in cheapest.items():
        ratio = row["energy_exact_over_overall"]
        lines.append(f"| {target} | {run(row['overall'])} | {run(row['energy_exact'])} | "
                     + ("-" if ratio is None else f"{ratio:.2f}") + " |")
    return lines


def write(path: pathlib.Path, results: dict) -> None:
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
    figures = [name for name in TITLES if name in results]
    for name in figures:
        lines.append(f"| {name} | {_status(results[name])} | {results[name]['wall_time_s']:.1f} |")
    used = [method for method in METHODS if any(method in results[name]["methods"] for name in figures)]
    lines += ["", "Methods: " + "; ".join(f"**{method}**: {METHODS[method].description}" for method in used) + "."]
    for name in figures:
        result = results[name]
        lines += ["", f"## {TITLES[name]}", ""]
        lines += [f"![{name}]({image})" for image in result["images"]]
        lines += [
            "",
            f"**Agreement with the paper: {_status(result)}.** {result['verdict']}",
            "",
            f"Wall time: {result['wall_time_s']:.1f} s (compilation included).",
            "",
            "Settings: " + "; ".join(f"{key} = {_number(value)}" for key, value in result["settings"].items()) + ".",
            "",
        ]
        if result.get("size_note"):
            lines += [f"**Reduced size:** {result['size_note']}", ""]
        lines += _table(result["methods"], _COLUMNS[name])
        lines += ["", _NOTES[name]]
        if name == "fig4":
            lines += ["", *_cheapest_table(result["cheapest_at_solution_error"])]
    path.write_text("\n".join(lines) + "\n")


def _status(result: dict) -> str:
    """The status shown: agrees, partly, or DISAGREES (loud: the one a reader must not
    miss)."""
    status = result.get("status", "agrees" if result["agrees"] else "disagrees")
    return "DISAGREES" if status == "disagrees" else status
