"""Sphinx configuration of the fenics_matdepth documentation (``make docs``).

The demos in ``demos/`` are jupytext "light" scripts; ``make notebooks`` (docs/run_notebooks.py)
converts and executes them into ``docs/demos/*.ipynb``, and this build renders those notebooks
with their outputs (text, matplotlib plots, the pyvista pictures they display).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sphinx.application import Sphinx

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
    # private helpers (protocols, base classes) named in the public signatures
    ("py:class", r"fenics_matdepth\.[a-z_.]+\._[A-Za-z].*"),
    ("py:class", r"(os\.PathLike|pathlib\..*)"),
]

# -- formulas offline: MathJax 2 from the system, copied into the site --------------------------
# sphinx.ext.mathjax loads MathJax 3 from a CDN by default, so without network the formulas show
# as raw LaTeX. Debian's libjs-mathjax (in the FEniCSx root) holds MathJax 2.7; the parts that
# TeX input with CommonHTML output needs (about 1.5 MB of its 54 MB) are copied into the built
# site's _static/mathjax, so docs/_build/html reads offline. Without that package the CDN stays.

MATHJAX_SOURCE = Path("/usr/share/javascript/mathjax")
MATHJAX_PARTS = (
    "MathJax.js",
    "config/TeX-AMS_CHTML.js",
    "jax/input/TeX",
    "jax/element",
    "jax/output/CommonHTML",
    "extensions",
    "fonts/HTML-CSS/TeX/woff",
)
LOCAL_MATHJAX = (MATHJAX_SOURCE / "MathJax.js").is_file()
if LOCAL_MATHJAX:
    mathjax_path = "mathjax/MathJax.js?config=TeX-AMS_CHTML"  # relative to _static
    # myst would write a MathJax 3 configuration; MathJax 2 takes its own, which processes the
    # spans and blocks Sphinx writes (class "math", \(...\) and \[...\] delimiters).
    myst_update_mathjax = False
    mathjax2_config = {
        "tex2jax": {
            "inlineMath": [["\\(", "\\)"]],
            "displayMath": [["\\[", "\\]"]],
            "processEscapes": True,
            "processEnvironments": True,
        },
        # long display formulas break at their operators instead of running off the column
        "CommonHTML": {"linebreaks": {"automatic": True}},
    }


def copy_mathjax(app: Sphinx, exception: Exception | None) -> None:
    """Copy the MathJax parts the pages load into the built site's ``_static/mathjax``."""
    if exception is not None or not LOCAL_MATHJAX or app.builder.format != "html":
        return
    target = Path(app.outdir) / "_static" / "mathjax"
    for part in MATHJAX_PARTS:
        source = MATHJAX_SOURCE / part
        if source.is_dir():
            shutil.copytree(source, target / part, dirs_exist_ok=True)
        else:
            (target / part).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, target / part)


def setup(app: Sphinx) -> dict[str, bool]:
    """Register the MathJax copy (see ``copy_mathjax``)."""
    app.connect("build-finished", copy_mathjax)
    return {"parallel_read_safe": True, "parallel_write_safe": True}


# -- HTML --------------------------------------------------------------------------------------

html_theme = "sphinx_book_theme"
html_title = "fenics_matdepth"
html_theme_options = {"show_toc_level": 2}
suppress_warnings = ["mystnb.unknown_mime_type"]
