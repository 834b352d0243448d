"""The public API: what ``import fenics_matdepth as fm`` offers, and that the docs cover it.

A name added to or removed from ``fm.__all__`` must be added to or removed from ``PUBLIC`` here
and documented in ``docs/api.md``: the API changes only on purpose.
"""

from __future__ import annotations

import inspect
import re
import warnings
from pathlib import Path

import pytest

import fenics_matdepth as fm

DOCS = Path(__file__).resolve().parent.parent / "docs"

PUBLIC = {
    # the model: depth, operator, penalty
    "material_depth", "depth_deficiency", "DepthDeficiencyWarning", "ContactOperator",
    "propose_penalty", "Coulomb",
    # problems and their results
    "SystemAssembler", "ContactProblem", "NonlinearContactProblem", "rigid_body_modes",
    "solve_nonlinear", "SolveResult", "Solvable",
    "FreeBody", "FreeBodyDamping", "find_free_bodies",
    # stepping
    "solve_load_steps", "StepControl", "LoadStep", "StopRequested", "solve_time_steps", "TimeStep",
    "Newmark", "BackwardEuler", "Checkpoint", "PseudoTransient",
    "LocalRelaxation",
    # wrappers over a problem
    "AugmentedLagrangian", "UzawaUpdate", "RigidModeDamping", "damping_energy",
    "PenaltyContinuation", "ContinuationStage",
    # kinematics
    "RigidRotation", "rotation_displacement", "rotation_matrix",
    # submodules
    "checkpoint", "contact", "geometry", "kinematics", "materials", "meshing",
    "__version__",
}  # fmt: skip

#: Public names of subpackages, reached as ``fm.<module>.<name>``.
SUBMODULE_PUBLIC = {
    "contact.kernels": ("pair_energy", "collocation_energy", "augmented_pair_energy",
                        "pressure_moments"),
    "geometry": ("intersection_polygon",),
    "meshing": ("gmsh_model_to_mesh", "gmsh_build_to_mesh", "create_tetrahedral_mesh",
                "interpolation_points", "box_tetrahedra"),
}  # fmt: skip


def test_all_lists_exactly_the_public_names():
    assert set(fm.__all__) == PUBLIC
    assert len(fm.__all__) == len(PUBLIC)  # no name listed twice


@pytest.mark.parametrize("name", sorted(PUBLIC - {"__version__"}))
def test_every_public_name_exists_and_has_a_docstring(name):
    obj = getattr(fm, name)
    assert inspect.getdoc(obj), f"fm.{name} has no docstring"


@pytest.mark.parametrize(
    "path", [f"{m}.{n}" for m, names in SUBMODULE_PUBLIC.items() for n in names]
)
def test_submodule_public_names(path):
    obj = fm
    for part in path.split("."):
        obj = getattr(obj, part)
    assert callable(obj) and inspect.getdoc(obj), path


def test_every_public_name_is_in_the_api_reference():
    """docs/api.md names every public class and function (autodoc ``:members:`` or a section)."""
    text = (DOCS / "api.md").read_text()
    words = set(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", text))
    missing = sorted(
        n
        for n in PUBLIC - {"__version__"}
        if n not in words and not inspect.ismodule(getattr(fm, n))
    )
    assert missing == []
    for module in ("materials", "kinematics", "meshing", "checkpoint", "contact.kernels"):
        assert f"fenics_matdepth.{module}" in text, module


def test_the_old_assembler_name_still_works_with_a_warning():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = fm.ContactAssembler
    assert old is fm.SystemAssembler
    assert any(issubclass(w.category, DeprecationWarning) for w in caught)


def test_unknown_attribute_raises_attribute_error():
    with pytest.raises(AttributeError, match="no_such_name"):
        _ = fm.no_such_name
