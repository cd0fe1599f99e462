"""The experiments' verdicts come from stated criteria alone: every check carries its
criterion, a failed secondary check makes an experiment "partly", any other failed
check "disagrees", and Figure 1's verdict flips when a method is pushed outside a
criterion (synthetic measurements, no runs)."""

import pytest

from nhjax._reproduce import fig1
from nhjax._reproduce._common import check, verdict


def test_the_status_follows_the_checks():
    main, aside = check(True, "order 2.0", "in [1.8, 2.2]"), check(True, "slope 1", "factor 3", secondary=True)
    assert verdict([main, aside])["status"] == "agrees"
    assert verdict([main, {**aside, "passed": False}])["status"] == "partly"
    assert verdict([{**main, "passed": False}, aside])["status"] == "disagrees"
    assert verdict([{**main, "passed": False}, {**aside, "passed": False}])["status"] == "disagrees"
    judged = verdict([main, {**aside, "passed": False}])
    assert judged["agrees"] is False
    assert judged["verdict"] == "Partly: order 2.0 [criterion: in [1.8, 2.2]]; NOT slope 1 [criterion: factor 3]."


BOUND = 1e-12


def _runs(**slopes):
    """Figure 1's measurements as a run would give them: the discrete gradients at
    roundoff, the comparison methods with the variance slopes given (in units of the
    line 1e-4 h^4)."""
    runs = {
        name: dict(max_constraint_error=1e-15, max_relative_energy_error_all=1e-14, final_variance_over_h4=0.0)
        for name in ("AVF", "GONZALEZ")
    }
    for name, slope in slopes.items():
        runs[name] = dict(max_constraint_error=1e-15, max_relative_energy_error=1e-4, slope_over_reference=slope)
    return runs


def _status(**slopes):
    runs = _runs(**slopes)
    orders = {name: 2.0 for name in runs}
    comparison = [name for name in runs if name not in ("AVF", "GONZALEZ")]
    claims = fig1.checks(orders, runs, ["AVF", "GONZALEZ"], comparison, BOUND)
    assert all(claim["criterion"] for claim in claims)
    return verdict(claims)


@pytest.mark.parametrize(
    "slopes, status",
    [
        (dict(SI_DLA=1.0, I_DLA=1.5, SPARK=0.8), "agrees"),
        (dict(SI_DLA=1.0, I_DLA=18.0, SPARK=0.8), "partly"),  # I-DLA 18x the line
        (dict(SI_DLA=1.0, I_DLA=1.5, SPARK=0.2), "partly"),
        (dict(SI_DLA=10.0, I_DLA=1.5, SPARK=0.8), "disagrees"),  # SI-DLA off the line
    ],
)
def test_figure_1_flips_when_a_slope_leaves_its_criterion(slopes, status):
    judged = _status(**{name.replace("_", "-"): value for name, value in slopes.items()})
    assert judged["status"] == status, judged["verdict"]
    assert "criterion: within a factor 3" in judged["verdict"]


def test_figure_1_disagrees_when_a_discrete_gradient_loses_energy():
    runs = _runs(**{"SI-DLA": 1.0})
    runs["GONZALEZ"]["max_relative_energy_error_all"] = 1e-9
    claims = fig1.checks({name: 2.0 for name in runs}, runs, ["AVF", "GONZALEZ"], ["SI-DLA"], BOUND)
    judged = verdict(claims)
    assert judged["status"] == "disagrees"
    assert "NOT discrete-gradient energy error 1.0e-09" in judged["verdict"]
