"""The synthetic leg of the knee demo (meshes/leg.py): what its geometry promises."""

from __future__ import annotations

import math

from mpi4py import MPI

import numpy as np
import pytest

from fenics_matdepth._compat import geometry_dofmap
from meshes import leg


def _inside_polygon(points: np.ndarray, corners: list[tuple[float, float]]) -> np.ndarray:
    """Even-odd test of 2D points (n, 2) against a simple polygon."""
    inside = np.zeros(len(points), dtype=bool)
    for (y0, z0), (y1, z1) in zip(corners, corners[1:] + corners[:1], strict=True):
        crosses = (z0 > points[:, 1]) != (z1 > points[:, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            y_cut = y0 + (points[:, 1] - z0) * (y1 - y0) / (z1 - z0)
        inside ^= crosses & (points[:, 0] < y_cut)
    return inside


@pytest.mark.serial
def test_the_popliteal_space_is_empty_of_tissue_and_covered_by_skin():
    """No soft tissue is left in the slot behind the knee (the tissue that a flexion of 150
    degrees about the fixed axis would rotate into the femoral shaft), the skin-fat layer
    covers it, and the calf tissue in front of its lower face (glued to the tibia) stays."""
    g = leg.LegGeometry()
    mesh, cell_tags, _ = leg.leg_mesh(MPI.COMM_SELF, "coarse", g)
    stats = leg.mesh_statistics(mesh)
    assert stats["inverted"] == 0, stats
    nodes = np.asarray(geometry_dofmap(mesh))
    centroids = mesh.geometry.x[nodes].mean(axis=1)
    body = np.empty(len(centroids), dtype=np.int32)
    body[cell_tags.indices] = cell_tags.values
    w = g.popliteal_space_half_width
    a = math.radians(g.popliteal_space_angle)
    corners = g.popliteal_space_outline
    in_slot = (np.abs(centroids[:, 0]) < w) & _inside_polygon(centroids[:, 1:], corners)
    soft = np.isin(body, [leg.QUADRICEPS, leg.TENDON, leg.LIGAMENT, leg.THIGH, leg.CALF])
    assert w > 0.0 and not np.any(in_slot & soft), centroids[in_slot & soft][:5]
    # the skin-fat layer closes the slot behind, at the crease's level and above and below it
    behind = (np.abs(centroids[:, 0]) < w) & (centroids[:, 1] < -25.0)
    for z in (g.crease_level, 10.0, 30.0):
        near = behind & (np.abs(centroids[:, 2] - z) < 5.0)
        assert np.any(near & (body == leg.SKIN)), z
        assert not np.any(near & soft), centroids[near & soft][:5]
    # in front of the lower face, behind the tibial shaft: calf tissue (glued to the tibia)
    lower = (
        (np.abs(centroids[:, 0]) < w)
        & (centroids[:, 2] < -30.0)
        & (centroids[:, 2] > -45.0)
        & (centroids[:, 1] > -math.tan(a) * np.abs(centroids[:, 2]))
        & (centroids[:, 1] < g.tibia_shaft_offset - g.tibia_shaft_radius)
    )
    assert np.any(lower & (body == leg.CALF))
