"""The documentation site builds with `mkdocs build --strict`: a broken cross-reference,
a missing page or an object that no longer exists fails it."""

import pathlib
import subprocess
import sys


ROOT = pathlib.Path(__file__).resolve().parent.parent


def test_the_site_builds_strictly(tmp_path):
    build = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )
    assert build.returncode == 0, build.stderr[-5000:]
    methods = (tmp_path / "site" / "methods" / "index.html").read_text()
    for name in ("GonzalezR", "GonzalezF", "SIDLA", "IDLA", "SPARK", "Composition", "DiscreteGradient"):
        assert f'id="nhjax.{name}"' in methods, name
    # The tables of methods and examples are read from the registry and the catalogue.
    from nhjax._methods import METHODS
    from nhjax.examples import EXAMPLES

    for name in METHODS:
        assert f"<code>{name}</code>" in methods, name
    systems = (tmp_path / "site" / "systems" / "index.html").read_text()
    for name in EXAMPLES:
        assert f"<code>{name}</code>" in systems, name
    assert "hooks" not in {path.name for path in (tmp_path / "site").iterdir()}
    assert (tmp_path / "site" / "notebooks" / "sleigh_parameter_identification" / "index.html").exists()
    reproduction = (tmp_path / "site" / "reproduction" / "report" / "index.html").read_text()
    assert "fig1.png" in reproduction and "Mode: full" in reproduction
