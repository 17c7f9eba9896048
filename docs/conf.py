"""Sphinx configuration: the API reference of clumpylen_jax, from its docstrings.

Build: ``sphinx-build -b html docs docs/_build`` (tests/test_docs.py builds it).
"""

import os
import sys

sys.path.insert(0, os.path.abspath(".."))

project = "clumpylen_jax"
author = "clumpylen_jax contributors"
extensions = ["sphinx.ext.autodoc"]
autodoc_member_order = "bysource"
autodoc_typehints = "none"          # signatures as written; units live in names and docstrings
exclude_patterns = ["_build"]
html_theme = "alabaster"
nitpicky = False


def _verbatim(app, what, name, obj, options, lines):
    """The package's docstrings are plain text (units, formulas in Unicode), not reST:
    show them as written, in a literal block, rather than let reST misread them."""
    if lines:
        lines[:] = ["::", ""] + ["    " + line for line in lines] + [""]


def setup(app):
    app.connect("autodoc-process-docstring", _verbatim)
