import subprocess
import sys


def _run(*arguments):
    return subprocess.run(
        [sys.executable, "-m", "nhjax", *arguments], capture_output=True, text=True, timeout=300
    )


def test_demo_reports_conserved_energy_and_constraints():
    out = _run("demo", "--steps", "400")
    assert out.returncode == 0, out.stderr
    lines = {line.split("  ")[1].strip(): line.split()[-1] for line in out.stdout.splitlines() if "max " in line}
    for name, value in lines.items():
        assert float(value) < 1e-13, (name, value)
    assert len(lines) == 3


def test_bad_arguments_give_a_message_and_nonzero_exit():
    out = _run("demo", "--dt", "-1")
    assert out.returncode != 0 and "--dt must be positive" in out.stderr
    out = _run("fly")
    assert out.returncode != 0 and "invalid choice" in out.stderr
