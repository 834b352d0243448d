"""Sphinx configuration of the fenics_matdepth documentation (``make docs``).

The demos in ``demos/`` are jupytext "light" scripts; ``make notebooks`` (docs/run_notebooks.py)
converts and executes them into ``docs/demos/*.ipynb``, and this build renders those notebooks
with their outputs (text, matplotlib plots, the pyvista pictures they display).
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))

import fenics_matdepth  # noqa: E402

project = "fenics_matdepth"
author = "the fenics_matdepth developers"
copyright = "2026, the fenics_matdepth developers"
release = version = fenics_matdepth.__version__

extensions = [
    "myst_nb",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
]

# -- the demos: notebooks executed by `make notebooks` (docs/run_notebooks.py) ---------------
# `make docs` renders them with the outputs they already hold, so each demo runs once.

nb_execution_mode = "off"
nb_merge_streams = True
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence"]
myst_heading_anchors = 3

source_suffix = {".md": "myst-nb", ".ipynb": "myst-nb"}
exclude_patterns = [
    "_build", "Thumbs.db", ".DS_Store", "**/__pycache__", "**/output", "demos/*.py",
]  # fmt: skip

# -- API reference ---------------------------------------------------------------------------

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": False}
# NamedTuple fields are described in their class's "Attributes:" section already.
napoleon_use_ivar = True
napoleon_google_docstring = True
napoleon_numpy_docstring = False
# `make docs` runs nitpicky (-n): every reference to this package's own objects must resolve.
# References to other packages' types cannot (no inventories without network at build time).
nitpick_ignore_regex = [
    (
        "py:.*",
        r"(numpy|np|ufl|dolfinx|basix|petsc4py|PETSc|mpi4py|MPI|numba|typing|pyvista)(\..*)?",
    ),
    ("py:.*", r"(Expr|Scalar|optional|callable|array_like|collections\.abc\..*)"),
    ("py:class", r"fenics_matdepth\.(solvers|dynamics|augmented|continuation)\._.*"),
    ("py:class", r"_Problem"),
    ("py:class", r"os\.PathLike"),
]

# -- HTML --------------------------------------------------------------------------------------

html_theme = "sphinx_book_theme"
html_title = "fenics_matdepth"
html_theme_options = {"show_toc_level": 2}
suppress_warnings = ["mystnb.unknown_mime_type"]
