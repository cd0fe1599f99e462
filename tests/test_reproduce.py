"""`nhjax reproduce` end to end at a reduced size: the files it writes, and the paper's
claims in its numbers.

One reproduction of all five figures runs once for the module (two methods on the
quartic, one of each kind; Figure 1's ensemble at the quick size, 200 states to
t = 500; 4000 gearbox steps in two chunks), in a child process whose XLA compiles as the
`nhjax` command's does (`_nhjax_command`, on one device), not at the suite's lowest
optimisation level: Figure 1's ensemble runs for far longer than it compiles, and runs
about three times slower at that level. Fewer states make the variance slopes of
Figure 1(d) a lottery: with 50, rounding-level changes in the chaotic ensemble moved
SI-DLA's slope from 0.27 to 0.1 of McLachlan & Perlmutter's line; with 200 it was
0.87."""

import dataclasses
import json
import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest

from nhjax._reproduce import figure, FIGURES, reproduce


# Two methods on the quartic, one of each kind; each figure's quick sizes otherwise.
SMALL = {
    "fig1": dataclasses.replace(figure("fig1").quick, methods=("SI-DLA", "GONZALEZ"), order_step_sizes=(0.1, 0.05, 0.025)),
    "fig2": dataclasses.replace(figure("fig2").quick, gonzalez_r=False),
    "fig3": dataclasses.replace(figure("fig3").quick, steps=4000, chunk_steps=2000),
    "fig4": dataclasses.replace(
        figure("fig4").quick,
        methods=("SI-DLA", "GONZALEZ"),
        step_sizes=(0.1, 0.05, 0.025),
        tolerances=(1e-6, 1e-9),
        repeats=1,
        compositions=("GONZALEZ order 4",),
        composition_step_sizes=(0.25, 0.125, 0.0625),
        collocations=("EP-COLLOCATION 4",),
    ),
}
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


_CHILD = """
import json, sys
from _nhjax_command import add_xla_flags, LOOP_EMITTER, WHOLE_LOOPS
add_xla_flags([LOOP_EMITTER, WHOLE_LOOPS])
from nhjax._reproduce import reproduce
from tests.test_reproduce import SMALL
figures, out, returned = json.loads(sys.argv[1]), sys.argv[2], sys.argv[3]
results = reproduce(figures, quick=True, out=out, progress=False, _sizes=SMALL)
with open(returned, "w") as file:
    json.dump(results, file)
"""


def _reproduce_in_child(figures, out: pathlib.Path) -> dict:
    """`reproduce(figures, quick=True, out=out, _sizes=SMALL)` in a child process with
    the command's XLA flags in place of the suite's (the module docstring): what it
    returned, through JSON."""
    returned = out.parent / f"{out.name}-returned.json"
    environment = {**os.environ, "XLA_FLAGS": ""}
    subprocess.run(
        [sys.executable, "-c", _CHILD, json.dumps(figures), str(out), str(returned)],
        cwd=pathlib.Path(__file__).parents[1], env=environment, check=True, timeout=1200,
    )
    return json.loads(returned.read_text())


@pytest.fixture(scope="module")
def reproduction(tmp_path_factory):
    out = tmp_path_factory.mktemp("reproduction")
    return out, _reproduce_in_child("all", out)


def test_writes_every_figure_results_and_report(reproduction):
    out, results = reproduction
    for name in FIGURES:
        image = (out / f"{name}.png").read_bytes()
        assert image.startswith(PNG_SIGNATURE) and len(image) > 10_000, name
    saved = json.loads((out / "results.json").read_text())
    assert saved == results
    for name in FIGURES:
        assert isinstance(saved[name]["agrees"], bool)
        assert saved[name]["status"] in ("agrees", "partly", "disagrees")
        assert saved[name]["verdict"].startswith(("Agrees", "Partly", "Disagrees", "Beyond the paper"))
        assert all(item["criterion"] for item in saved[name]["checks"])
        assert saved[name]["wall_time_s"] > 0
    assert saved["meta"]["figures"] == list(FIGURES)


def test_report_embeds_each_figure_with_its_verdict(reproduction):
    out, results = reproduction
    report = (out / "report.md").read_text()
    for name in FIGURES:
        assert f"![{name}]({name}.png)" in report
        assert results[name]["verdict"] in report
    assert report.count("Wall time:") == len(FIGURES)
    assert "**Reduced size:**" in report  # Figure 1's ensemble and Figure 3's run are short


def test_no_experiment_disagrees_with_the_paper(reproduction):
    """Figures 2 to 5 agree. Figure 1 agrees, or reads "partly" when only its secondary
    claim fails (I-DLA's and SPARK's variance slopes within a factor 3 of SI-DLA's
    line)."""
    _, results = reproduction
    verdicts = {name: results[name]["verdict"] for name in FIGURES}
    for name in FIGURES:
        failed = [item for item in results[name]["checks"] if not item["passed"]]
        expected = "agrees" if not failed else "partly"
        assert results[name]["status"] == expected, verdicts
        assert all(item["secondary"] for item in failed), verdicts
    assert all(results[name]["status"] == "agrees" for name in ("fig2", "fig3", "fig4", "fig5")), verdicts


def test_quartic_orders_energy_and_constraint(reproduction):
    """Figure 1: second order; GONZALEZ's energy error and its variance at roundoff,
    SI-DLA's O(h^2) with variance growing about as 1e-4 h^4 t; the constraint kept by both."""
    _, results = reproduction
    methods = results["fig1"]["methods"]
    for name in ("SI-DLA", "GONZALEZ"):
        assert 1.9 < methods[name]["fitted_order"] < 2.1, name
        assert methods[name]["max_constraint_error"] < 1e-14, name
    assert methods["GONZALEZ"]["max_relative_energy_error_all_states"] < 1e-12
    assert methods["SI-DLA"]["max_relative_energy_error"] > 1e-4
    assert abs(methods["GONZALEZ"]["final_variance_over_h4"]) < 1e-18
    # Within a factor 3 up to the ensemble's sampling error, the verdict's criterion: the
    # slope of a chaotic ensemble moves by its sampling error when the rounding changes.
    low, high = methods["SI-DLA"]["variance_slope_interval_relative_to_line"]
    assert low < methods["SI-DLA"]["variance_slope_relative_to_line"] < high
    assert low <= 3 and high >= 1 / 3
    assert high - low < 2, (low, high)


def test_sleigh_settles_as_proposition_4_1_says(reproduction):
    """Figure 2: from either side of the unstable equilibrium (0, -0.6), rho ends at
    (0, +sqrt(rho1^2 + rho2^2)), with the energy to roundoff."""
    _, results = reproduction
    result = results["fig2"]["methods"]["GONZALEZ"]
    settled = np.hypot(0.001, 0.6)
    np.testing.assert_allclose(result["final_rho"], [[0.0, settled], [0.0, settled]], rtol=0, atol=1e-12)
    assert result["max_relative_energy_error"] < 1e-13
    assert all(0 < time < 1000 for time in result["time_rho2_turns_positive"])


def test_gearbox_energy_and_constraint(reproduction):
    """Figure 3: GONZALEZ-R and -F keep the energy, SI-DLA does not; GONZALEZ-R and
    SI-DLA keep the constraint, GONZALEZ-F does not."""
    _, results = reproduction
    methods = results["fig3"]["methods"]
    energy = {name: methods[name]["max_relative_energy_error"] for name in methods}
    constraint = {name: methods[name]["max_constraint_error"] for name in methods}
    assert energy["GONZALEZ-R"] < 1e-13 and energy["GONZALEZ-F"] < 1e-13
    assert energy["SI-DLA"] > 1e-6
    assert constraint["GONZALEZ-R"] < 1e-14 and constraint["SI-DLA"] < 1e-14
    assert constraint["GONZALEZ-F"] > 1e-6


def test_work_precision(reproduction):
    """Figure 4: each point timed and measured; GONZALEZ's energy at roundoff at every
    step size, Dopri8's error falling with its tolerance."""
    _, results = reproduction
    methods = results["fig4"]["methods"]
    assert set(methods) == {
        "SI-DLA", "GONZALEZ", "GONZALEZ order 4", "EP-COLLOCATION 4", "Dopri8 (adaptive)",
        "Dopri8 + projection (adaptive)",
    }
    for entry in methods.values():
        assert len(entry["wall_time_s"]) == len(entry["settings"]) and not entry["failed"]
        assert all(seconds > 0 for seconds in entry["wall_time_s"])
    assert methods["SI-DLA"]["steps"] == [100, 200, 400]
    assert max(methods["GONZALEZ"]["energy_error"]) < 1e-13
    assert min(methods["SI-DLA"]["energy_error"]) > 1e-6
    dopri8 = methods["Dopri8 (adaptive)"]["solution_error"]
    assert dopri8[1] < 1e-2 * dopri8[0]  # tolerances 1e-6 and 1e-9
    projected = methods["Dopri8 + projection (adaptive)"]
    assert max(projected["energy_error"]) < 1e-14
    assert projected["solution_error"][1] < 1e-2 * projected["solution_error"][0]
    composed = methods["GONZALEZ order 4"]
    assert max(composed["energy_error"]) < 1e-13
    assert 3.7 <= composed["fitted_order"] <= 4.6
    collocation = methods["EP-COLLOCATION 4"]
    assert max(collocation["energy_error"]) < 1e-13
    assert 3.7 <= collocation["fitted_order"] <= 4.6


def test_work_precision_names_the_cheapest_runs(reproduction):
    """At each target error: the cheapest run of all those that reach it, and the
    cheapest energy-exact one (recomputed here from the runs), in results and report."""
    out, results = reproduction
    methods = results["fig4"]["methods"]
    cheapest = results["fig4"]["cheapest_at_solution_error"]
    assert list(cheapest) == ["0.001", "1e-06", "1e-09"]
    exact = ("GONZALEZ", "GONZALEZ order 4", "Dopri8 + projection (adaptive)")
    for target, row in cheapest.items():
        runs = [(seconds, name) for name, entry in methods.items()
                for seconds, error in zip(entry["wall_time_s"], entry["solution_error"]) if error <= float(target)]
        if not runs:
            assert row["overall"] is None
            continue
        assert (row["overall"]["wall_time_s"], row["overall"]["method"]) == min(runs)
        exact_runs = [run for run in runs if run[1] in exact]
        if exact_runs:
            assert (row["energy_exact"]["wall_time_s"], row["energy_exact"]["method"]) == min(exact_runs)
            assert row["energy_exact_over_overall"] >= 1
    report = (out / "report.md").read_text()
    assert "| error at t = 10 | cheapest run | cheapest energy-exact run | ratio |" in report


def test_contact_oscillator_reversibility(reproduction):
    """Figure 5: the discrete gradients keep the energy in both forms; the second first
    integral H_y stays near its value on the reversible form and drifts, ten times and
    more, on the gauge-shifted one."""
    _, results = reproduction
    methods = results["fig5"]["methods"]
    assert results["fig5"]["status"] == "agrees", results["fig5"]["verdict"]
    for name in ("GONZALEZ", "AVF"):
        reversible, shifted = methods[f"{name}, reversible form"], methods[f"{name}, gauge-shifted form"]
        assert max(reversible["max_relative_energy_error"], shifted["max_relative_energy_error"]) < 1e-13
        assert shifted["max_y_energy_error"] > 10 * reversible["max_y_energy_error"]
        assert reversible["y_energy_error_growth"] < 1.5 < shifted["y_energy_error_growth"]
    assert methods["SI-DLA, canonical form"]["max_relative_energy_error"] > 1e-6
    projected = methods["Dopri8 + projection, reversible form"]
    assert projected["max_relative_energy_error"] < 1e-14 and projected["y_energy_error_growth"] > 2


def test_an_interrupted_reproduction_resumes_to_the_same_numbers(reproduction, tmp_path):
    """The gearbox run with a chunk missing, as after an interruption: a rerun into the
    same folder recomputes just that chunk, and every number comes out the same."""
    out, results = reproduction
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    chunk = copy / "chunks" / "fig3_GONZALEZ-R_4000" / "chunk_00001.npz"
    kept = copy / "chunks" / "fig3_GONZALEZ-R_4000" / "chunk_00000.npz"
    kept_time = kept.stat().st_mtime_ns
    chunk.unlink()
    again = _reproduce_in_child(["fig3"], copy)
    assert chunk.exists() and kept.stat().st_mtime_ns == kept_time
    assert again["fig3"]["methods"] == results["fig3"]["methods"]
    assert list(json.loads((copy / "results.json").read_text())["meta"]["figures"]) == ["fig3"]


@pytest.mark.parametrize("figures", [["fig6"], [], "fig1,fig2"])
def test_unknown_figures_are_refused(figures, tmp_path):
    with pytest.raises(ValueError, match="choose from fig1, fig2, fig3, fig4, fig5 or all"):
        reproduce(figures, quick=True, out=tmp_path, progress=False)
    assert not any(tmp_path.iterdir())


def test_each_figure_is_one_record_the_report_reads(reproduction):
    """Each experiment's record names it, sizes it at both sizes with one class, and
    gives the report its title, table and note: the report shows exactly those."""
    _, results = reproduction
    out, _ = reproduction
    report = (out / "report.md").read_text()
    for name in FIGURES:
        record = figure(name)
        assert record.name == name
        assert dataclasses.is_dataclass(record.full) and type(record.quick) is type(record.full)
        assert f"## {record.title}\n" in report
        assert "| method | " + " | ".join(record.columns) + " |" in report
        assert record.note in report
        assert set(record.columns) <= set(next(iter(results[name]["methods"].values())))
