"""The API reference (docs/, Sphinx autodoc) builds from the docstrings, warning-free,
and documents every public name (`clumpylen_jax.__all__`)."""

from pathlib import Path

import pytest

import clumpylen_jax

sphinx_cmd = pytest.importorskip("sphinx.cmd.build", reason="sphinx (docs extra) not installed")
DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_api_reference_builds_and_covers_the_public_api(tmp_path):
    status = sphinx_cmd.build_main(["-q", "-W", "-b", "html", "-d", str(tmp_path / "doctrees"),
                                    str(DOCS), str(tmp_path / "html")])
    assert status == 0
    html = (tmp_path / "html" / "index.html").read_text(encoding="utf-8")
    missing = [n for n in clumpylen_jax.__all__
               if n not in ("__version__", "ACCURACY_PRESETS") and f"{n}</span>" not in html
               and f">{n}<" not in html]
    assert not missing, missing
