"""A synthetic right leg around the knee (gmsh OCC): bones, tendons, muscles and a skin-fat layer.

An anatomically plausible stand-in for the Visible Human leg of Hirota, Fisher & State (2003),
section 6 (their Fig. 18), built from primitives so that it can be shipped and regenerated.
Units: millimetres. Axes: ``x`` medial-lateral (the knee's flexion axis is the ``x`` axis),
``y`` anterior (the patella is at ``y > 0``), ``z`` proximal (the hip is up). The flexion axis
passes through the origin, the centres of the two femoral condyles, so that a rigid rotation
of the tibia about it keeps the joint space open, as in a real knee.

Bodies (cell tags, one physical group each):

=====================  =====  =============================================================
body                   tag    shape
=====================  =====  =============================================================
femur                  1      shaft (cylinder) with two spherical condyles; the trochlear
                              groove is the saddle between the condyles, anteriorly
tibia                  2      shaft with an elliptic plateau and the tibial tuberosity
patella                3      a thick lens (ellipsoid) in front of the trochlear groove
quadriceps             4      the anterior thigh above the patella, sliding on the femur
quadriceps tendon      5      quadriceps to patella (glued to both)
patellar ligament      6      patella to tibial tuberosity (glued to both)
thigh soft tissue      7      the rest of the thigh inside the skin (glued to the femur shaft
                              posteriorly, sliding on the distal femur)
calf soft tissue       8      the shank inside the skin (glued to the tibia)
skin-fat layer         9      a shell of thickness ``skin`` around the whole leg
=====================  =====  =============================================================

Glued interfaces (muscle-tendon, tendon-patella, ligament-patella, ligament-tibia,
muscle-skin, thigh tissue on the femur shaft, calf on the tibia) are shared surfaces of one
conforming mesh (gmsh ``fragment``). Sliding interfaces are *not* shared: a gap of ``gap``
separates the distal femur from everything around it (the patella, the quadriceps, the thigh
soft tissue), and the tibial plateau from the condyles (the joint space, a cavity bounded by
the condyles, the plateau and the soft tissue around them, reaching past the plateau's
posterior rim), and a recess of ``patella_recess`` round the patella up to
``patella_recess_top`` (swept back into the femur's clearance): soft tissue glued to bone
and pressed onto the femur there was crushed.
Behind the knee the popliteal fossa is a hollow (a cylinder along ``x`` cut out of the back of
the leg, lined with skin), and at its floor a crease (the popliteal crease: a slot of width
``2 * crease_half_width``, lined with skin) cuts into the back of the leg: where the skin folds
onto itself when the knee bends. Between the condyles' backs and the skin, at ``|x| <
popliteal_space_half_width``, the popliteal space is left empty (in a real knee: fat, vessels
and the tibial nerve, far softer than muscle): the calf tissue there would otherwise be rotated
into the femoral shaft by deep flexion about the fixed axis.

Facet tags: :data:`PROXIMAL_CUT` (the thigh's cut plane ``z = thigh_length``) and
:data:`DISTAL_CUT` (the shank's cut plane ``z = -shank_length``).

Mesh size: ``resolution`` scales every size (``coarse`` = 2.2, ``default`` = 1,
``fine`` = 0.7, or a number); at 1 the skin and the articular surfaces are meshed with about
``h_surface`` = 5 mm, the interior with ``h_interior`` = 9 mm. The skin (8 mm) is then about two
elements thick, so that few tetrahedra have all four vertices on the boundary.

Run ``python3 meshes/leg.py [--resolution coarse|default|fine|NUMBER]`` to mesh the leg, print
its statistics (vertices, tetrahedra, boundary triangles, tetrahedra with all four vertices on
the boundary, minimum volume) and write ``output/leg.xdmf``.
"""

from __future__ import annotations

import dataclasses
import math

from mpi4py import MPI

import dolfinx
import numpy as np

from fenics_matdepth.meshing import gmsh_build_to_mesh

__all__ = [
    "BODIES",
    "CALF",
    "DISTAL_CUT",
    "FEMUR",
    "LIGAMENT",
    "PATELLA",
    "PROXIMAL_CUT",
    "QUADRICEPS",
    "RESOLUTIONS",
    "SKIN",
    "TENDON",
    "THIGH",
    "TIBIA",
    "LegGeometry",
    "build_leg_model",
    "leg_mesh",
    "mesh_statistics",
]

#: Cell tags of the bodies.
FEMUR, TIBIA, PATELLA, QUADRICEPS, TENDON, LIGAMENT, THIGH, CALF, SKIN = range(1, 10)
#: Body names by cell tag.
BODIES = {
    FEMUR: "femur",
    TIBIA: "tibia",
    PATELLA: "patella",
    QUADRICEPS: "quadriceps",
    TENDON: "quadriceps_tendon",
    LIGAMENT: "patellar_ligament",
    THIGH: "thigh_soft_tissue",
    CALF: "calf_soft_tissue",
    SKIN: "skin_fat",
}
#: Facet tags: the thigh's proximal cut plane and the shank's distal cut plane.
PROXIMAL_CUT, DISTAL_CUT = 1, 2
#: Named mesh-size scales.
RESOLUTIONS = {"coarse": 2.2, "default": 1.0, "fine": 0.75}


@dataclasses.dataclass(frozen=True)
class LegGeometry:
    """Dimensions of the synthetic leg (mm). Defaults: an adult male knee, rounded figures.

    Attributes:
        thigh_length: height of the thigh's proximal cut above the flexion axis.
        shank_length: depth of the shank's distal cut below the flexion axis.
        thigh_radius: outer radius of the thigh at its cut (skin surface).
        knee_radius: outer radius at the knee (``z = knee_level``).
        ankle_radius: outer radius of the shank at its cut.
        knee_level: height of the narrowest, knee section of the envelope.
        skin: thickness of the skin-fat layer (skin + subcutaneous fat, 3 mm to 1 cm).
        femur_shaft_radius: radius of the femoral shaft.
        femur_shaft_offset: anterior offset ``y`` of the shaft's axis (the condyles bulge
            backwards, as the posterior condylar offset of a real femur).
        metaphysis_offset: ``y`` of the shaft's axis where it meets the condyles (``z = 0``).
            Between ``z = 0`` and ``z = metaphysis_height`` the shaft's axis sweeps forwards
            from here to ``femur_shaft_offset`` (a sheared cylinder), so that the anterior
            cortex runs into the trochlea without a step: a shaft kept straight down to the
            condyles stands 7 mm proud of the trochlear groove, a ledge under which the tissue
            below the patella is crushed as the patella slides down.
        metaphysis_height: height of that transition.
        condyle_radius: radius of the two spherical condyles, centred on the flexion axis.
        condyle_half_distance: ``x`` of the condyle centres (the notch and the trochlear groove
            are the saddle between them).
        gap: width of the sliding interfaces (joint space at the condyles' clearance).
        plateau_semi_axes: ``(x, y)`` semi-axes of the elliptic tibial plateau.
        plateau_offset: anterior offset ``y`` of the plateau's centre. With the shafts'
            offsets it keeps the bones apart at 150 degrees of flexion about a fixed axis (a
            real knee rolls back instead).
        plateau_thickness: height of the plateau.
        joint_space_semi_axes: ``(x, y)`` semi-axes of the joint-space cavity, an elliptic
            cylinder from the plateau up into the condyles' clearance (inside the plateau's
            rim, which the soft tissue holds).
        joint_space_offset: ``y`` of its centre. Its posterior edge lies 4 mm behind the
            plateau's (under the condyles): soft tissue left on the plateau's posterior rim was
            the leg's lowest det F (0.28 at 54 degrees), pressed between the rim, swinging up
            behind the condyles, and the femur; a real plateau's rim carries the meniscus and
            the capsule, which slide on the femur, not tissue glued to bone on both sides.
        joint_space_top: ``z`` of its top (inside the clearance spheres).
        tibia_shaft_radius: radius of the tibial shaft.
        tibia_shaft_offset: anterior offset ``y`` of the tibial shaft's axis.
        tuberosity_radius: radius of the tibial tuberosity (a ball on the anterior tibia).
        patella_semi_axes: ``(x, y, z)`` semi-axes of the patella (a thick lens).
        patella_height: ``z`` of the patella's centre with the knee straight.
        patellofemoral_space: distance between the patella and the femur (less than ``gap``).
            With a layer of soft tissue left between them (as when the patella sat ``2 gap``
            off the femur), that layer carried the patellofemoral pressure and was crushed
            as the patella slid down (det F 0.58 at 21 degrees).
        patella_recess: width of a sliding gap round the patella's posterior half (0: the
            tissue is glued all round its rim). Tissue glued to the back of the patella's rim
            was carried down onto the trochlea as the patella slid and tilted, and pressed
            into it (penetration 0.28 h, about 2 MPa, at 52 degrees); in a real knee the
            synovial recesses and the fat pad slide there. The tendon and ligament stay glued.
        patella_recess_depth: how much further back (``-y``) than the patella the recess
            reaches (the patella's outline swept back into the femur's clearance). 14 mm
            (was 8) empties the thigh tissue lateral to the patella's back that lay flat on the
            femur where the knee first stalled (docs/demos.md, the knee): from 0 degrees the
            coarse leg went on to 63.2 against 52.8 degrees with 8 mm (quadratic pressure term).
        patella_recess_top: height of the recess's flat roof above the patella's centre
            (``z``). At -2 (below the equator) the thigh tissue on the roof, between the
            patella's upper back and the femur, was crushed and stalled Newton's method at
            63.2 degrees (det F 0.20); at 8 the coarse leg passed 87 degrees.
        fat_pad_half_width: half width (``x``) of a box emptied between the patellar
            ligament and the femur, from the tibial plateau up to 12 mm below the patella's
            centre (default 0: none; the ligament itself stays), where a real knee has the
            infrapatellar fat pad. Tried at 10 mm against the tissue crushed under the
            patella's lower pole (det F 0.62 at 24 degrees with the recess alone): that
            tissue then held, but with the ligament wrapping the femur directly the patella
            was pressed onto the femur and the film of tissue between the patella's upper
            back and the femur was crushed instead (det F 0.76 at 19.5, 0.28 at 25.5 degrees).
        fat_pad_y: ``(back, front)``, the ``y`` range of that box (its back inside the femur's
            clearance, its front at the ligament, which takes precedence).
        tendon_semi_axes: ``(x, y)`` semi-axes of the quadriceps tendon's section.
        tendon_length: length of the quadriceps tendon above the patella.
        ligament_semi_axes: ``(x, y)`` semi-axes of the patellar ligament's section.
        quadriceps_start: ``z`` where the quadriceps begins (above the patella).
        attachment_level: above this ``z`` the thigh tissue is glued to the back of the femoral
            shaft (below it, and in front, it slides: the clearance gap).
        crease_level: ``z`` of the popliteal crease (and of the fossa's centre) behind the knee.
        fossa_depth: depth of the popliteal fossa (the hollow behind the knee) below the skin
            surface of the envelope, at ``x = 0``.
        fossa_radius: radius of the cylinder (along ``x``) that cuts the fossa; the hollow
            spans about ``2 sqrt(2 fossa_radius fossa_depth)`` along ``z`` and fades out
            sideways where the round back of the leg passes behind the cylinder.
        crease_depth: how far the crease cuts into the back of the leg below the fossa's floor.
        crease_half_width: half the opening of the crease.
        crease_half_length: half its extent along ``x``.
        popliteal_space_half_width: half width (``x``) of the popliteal space, a slot emptied
            behind the knee between the heads of gastrocnemius and the hamstrings (0: none).
            In a real knee it holds fat, the popliteal vessels and the tibial nerve, far softer
            than muscle; here it is left out. Without it the tissue behind the knee at
            ``x = 0`` was crushed at deep flexion: the calf tissue behind the tibial plateau
            rotates about the flexion axis into the femoral shaft's place (anything more than
            ``180 - 150 = 30`` degrees behind the shank's axis does by 150 degrees), and the
            coarse leg stopped at 135.8 degrees with det F 0.047 in the calf tissue at
            ``(0, -32, -5)`` and the thigh tissue between the condyles pressed into the femur.
            The skin-fat layer stays: it covers the slot, lines the crease and folds into the
            slot as the knee bends. Wider than the femoral shaft, so that the shaft never meets
            its sides.
        popliteal_space_angle: the slot's lower face, a plane through the flexion axis this
            many degrees behind the shank's axis (degrees): the calf tissue behind it is
            left out; the tissue in front of it, glued to the tibia, turns up against the
            femur's back at ``180 - popliteal_space_angle`` degrees of flexion.
        popliteal_space_reach: how far from the flexion axis that lower face reaches (mm).
        popliteal_space_top: ``z`` of the slot's top, behind the femoral shaft.
    """

    thigh_length: float = 100.0
    shank_length: float = 110.0
    thigh_radius: float = 58.0
    knee_radius: float = 54.0
    ankle_radius: float = 44.0
    knee_level: float = -35.0
    skin: float = 8.0
    femur_shaft_radius: float = 11.0
    femur_shaft_offset: float = 12.0
    metaphysis_offset: float = 3.0
    metaphysis_height: float = 24.0
    condyle_radius: float = 22.0
    condyle_half_distance: float = 15.0
    gap: float = 2.0
    plateau_semi_axes: tuple[float, float] = (36.0, 17.0)
    plateau_offset: float = 4.5
    plateau_thickness: float = 20.0
    joint_space_semi_axes: tuple[float, float] = (34.0, 16.5)
    joint_space_offset: float = 0.0
    joint_space_top: float = -8.0
    tibia_shaft_radius: float = 12.0
    tibia_shaft_offset: float = 6.0
    tuberosity_radius: float = 10.0
    patella_semi_axes: tuple[float, float, float] = (19.0, 8.0, 21.0)
    patella_height: float = 24.0
    patellofemoral_space: float = 1.5
    patella_recess: float = 2.0
    patella_recess_depth: float = 14.0
    patella_recess_top: float = 8.0
    fat_pad_half_width: float = 0.0
    fat_pad_y: tuple[float, float] = (10.0, 30.0)
    tendon_semi_axes: tuple[float, float] = (12.0, 5.0)
    tendon_length: float = 32.0
    ligament_semi_axes: tuple[float, float] = (8.0, 3.5)
    quadriceps_start: float = 58.0
    attachment_level: float = 34.0
    crease_level: float = -16.0
    fossa_depth: float = 14.0
    fossa_radius: float = 40.0
    crease_depth: float = 10.0
    crease_half_width: float = 2.0
    crease_half_length: float = 20.0
    popliteal_space_half_width: float = 14.0
    popliteal_space_angle: float = 30.0
    popliteal_space_reach: float = 55.0
    popliteal_space_top: float = 50.0

    @property
    def popliteal_space_outline(self) -> list[tuple[float, float]]:
        """Corners ``(y, z)`` of the popliteal space's outline in the y-z plane: in front, the
        femoral shaft's axis (the femur takes precedence); below, the plane
        ``popliteal_space_angle`` behind the shank's axis out to ``popliteal_space_reach``;
        behind, past the skin (the skin-fat layer takes precedence)."""
        a = math.radians(self.popliteal_space_angle)
        y_low = -self.popliteal_space_reach * math.sin(a)
        z_low = -self.popliteal_space_reach * math.cos(a)
        front, top = self.femur_shaft_offset, self.popliteal_space_top
        return [(front, top), (front, 0.0), (0.0, 0.0), (y_low, z_low), (-100.0, z_low),
                (-100.0, top)]  # fmt: skip

    @property
    def plateau_top(self) -> float:
        """``z`` of the tibial plateau: the joint space below the condyles is ``1.5 gap`` wide
        (wider than the clearance around the femur, so that the two do not touch)."""
        return -(self.condyle_radius + 1.5 * self.gap)

    def femur_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (mm, negative inside) from points ``(n, 3)`` to the femur."""
        d = np.full(points.shape[0], np.inf)
        for sign in (-1, 1):
            centre = np.array([sign * self.condyle_half_distance, 0.0, 0.0])
            d = np.minimum(d, np.linalg.norm(points - centre, axis=1) - self.condyle_radius)
        s = np.clip(points[:, 2] / self.metaphysis_height, 0.0, 1.0)
        axis_y = self.metaphysis_offset + s * (self.femur_shaft_offset - self.metaphysis_offset)
        radial = np.hypot(points[:, 0], points[:, 1] - axis_y)
        shaft = np.where(
            points[:, 2] >= 0.0,
            radial - self.femur_shaft_radius,
            np.hypot(np.maximum(radial - self.femur_shaft_radius, 0.0), points[:, 2]),
        )
        return np.minimum(d, shaft)

    @property
    def patella_centre(self) -> tuple[float, float, float]:
        """Centre of the patella: in front of the trochlea, ``patellofemoral_space`` clear of the
        femur. That is less than ``gap``: the patella takes the part of the femur's clearance it
        overlaps, so that its back faces the femur directly across the joint space (cartilage
        on cartilage in a real knee), with no soft tissue between them."""
        a, b, c = self.patella_semi_axes
        theta, phi = np.meshgrid(np.linspace(0, np.pi, 60), np.linspace(0, 2 * np.pi, 120))
        surface = np.column_stack(
            (
                a * (np.sin(theta) * np.cos(phi)).ravel(),
                b * (np.sin(theta) * np.sin(phi)).ravel(),
                c * np.cos(theta).ravel() + self.patella_height,
            )
        )
        lo, hi = 0.0, 80.0  # bisection on the centre's y
        for _ in range(50):
            y = 0.5 * (lo + hi)
            if self.femur_distance(surface + [0.0, y, 0.0]).min() < self.patellofemoral_space:
                lo = y
            else:
                hi = y
        return (0.0, hi, self.patella_height)

    @property
    def tuberosity_centre(self) -> tuple[float, float, float]:
        """Centre of the tibial tuberosity, on the anterior tibia below the plateau."""
        z = self.plateau_top - self.plateau_thickness - 6.0
        return (0.0, self.tibia_shaft_offset + self.tibia_shaft_radius + 4.0, z + 1.0)

    @property
    def ligament_ends(self) -> tuple[np.ndarray, np.ndarray]:
        """Centres of the patellar ligament's two ends: inside the patella, below its centre,
        and inside the tibia behind the tuberosity (mm). Its fibres run from the first to the
        second."""
        _, py, pz = self.patella_centre
        tx, ty, tz = self.tuberosity_centre
        top = np.array([0.0, py - 1.0, pz - 0.5 * self.patella_semi_axes[2]])
        bottom = np.array([tx, ty, tz])
        return top, bottom

    @property
    def ligament_axis(self) -> np.ndarray:
        """Unit vector along the patellar ligament (its fibre direction)."""
        top, bottom = self.ligament_ends
        return (bottom - top) / np.linalg.norm(bottom - top)

    #: Unit vector along the quadriceps tendon (its fibre direction).
    tendon_axis = (0.0, 0.0, 1.0)

    def outer_radius(self, z: float) -> float:
        """Outer (skin surface) radius of the envelope at height ``z`` (mm)."""
        if z >= self.knee_level:
            s = (z - self.knee_level) / (self.thigh_length - self.knee_level)
            return self.knee_radius + s * (self.thigh_radius - self.knee_radius)
        s = (self.knee_level - z) / (self.knee_level + self.shank_length)
        return self.knee_radius + s * (self.ankle_radius - self.knee_radius)


def _sizes(resolution: float | str) -> tuple[float, float, float]:
    """(surface size, interior size, elements per 2 pi of curvature)."""
    scale = RESOLUTIONS.get(resolution) if isinstance(resolution, str) else float(resolution)
    if scale is None or not scale > 0:
        raise ValueError(f"resolution must be one of {list(RESOLUTIONS)} or a positive number")
    return 6.0 * scale, 10.0 * scale, max(16.0, 16.0 / scale)


def build_leg_model(
    gmsh_model, geometry: LegGeometry | None = None, resolution: float | str = "default"
) -> None:
    """Build and mesh the leg in ``gmsh_model`` (call on one process only).

    Args:
        gmsh_model: ``gmsh.model`` of an initialised gmsh session; a new model is added.
        geometry: dimensions; default :class:`LegGeometry()`.
        resolution: ``"coarse"``, ``"default"``, ``"fine"`` or a size scale (1 = default).
    """
    import gmsh

    g = geometry or LegGeometry()
    h_surface, h_interior, per_turn = _sizes(resolution)
    occ = gmsh_model.occ
    gmsh_model.add("leg")

    def extrude_face(curves, dx, dy, dz):
        face = occ.addPlaneSurface([occ.addCurveLoop(curves)])
        return next(dt for dt in occ.extrude([(2, face)], dx, dy, dz) if dt[0] == 3)

    def ellipse_cylinder(x, y, z, height, ax, ay):
        """Elliptic cylinder along z (an exact ellipse extruded, not a scaled circle)."""
        if ax >= ay:
            return extrude_face([occ.addEllipse(x, y, z, ax, ay)], 0.0, 0.0, height)
        ellipse = occ.addEllipse(x, y, z, ay, ax)
        occ.rotate([(1, ellipse)], x, y, z, 0.0, 0.0, 1.0, math.pi / 2)
        return extrude_face([ellipse], 0.0, 0.0, height)

    def copy(dimtags):
        return occ.copy(dimtags)

    def fuse(dimtags):
        out, _ = occ.fuse(dimtags[:1], dimtags[1:])
        return out

    def cut(objects, tools, keep_tools=False):
        out, _ = occ.cut(objects, tools, removeObject=True, removeTool=not keep_tools)
        return out

    def femur_shape(extra):
        """The femur (extra = 0) or its clearance (extra = gap): shaft and two condyles."""
        r = g.condyle_radius + extra
        parts = [
            (3, occ.addSphere(sign * g.condyle_half_distance, 0.0, 0.0, r)) for sign in (-1, 1)
        ]
        radius = g.femur_shaft_radius + extra
        z1 = g.metaphysis_height
        parts.append(
            (3, occ.addCylinder(0.0, g.femur_shaft_offset, z1, 0.0, 0.0, g.thigh_length + 10 - z1,
                                radius))
        )  # fmt: skip
        # the metaphysis: a sheared cylinder from the condyles up to the straight shaft
        loops = [
            occ.addCurveLoop([occ.addCircle(0.0, y, z, radius)])
            for y, z in ((g.metaphysis_offset, 0.0), (g.femur_shaft_offset, z1))
        ]
        parts += [dt for dt in occ.addThruSections(loops, makeSolid=True, makeRuled=True)
                  if dt[0] == 3]  # fmt: skip
        return fuse(parts)

    # -- bones
    femur = cut(femur_shape(0.0), [(3, occ.addBox(-100, -100, g.thigh_length, 200, 200, 50))])
    z_plateau = g.plateau_top
    plateau = ellipse_cylinder(
        0.0,
        g.plateau_offset,
        z_plateau - g.plateau_thickness,
        g.plateau_thickness,
        *g.plateau_semi_axes,
    )
    shaft_bottom = -g.shank_length
    shaft_height = z_plateau - 5 - shaft_bottom  # up into the plateau
    tibia_shaft = (
        3,
        occ.addCylinder(0.0, g.tibia_shaft_offset, shaft_bottom, 0.0, 0.0, shaft_height,
                        g.tibia_shaft_radius),
    )  # fmt: skip
    tuberosity = (3, occ.addSphere(*g.tuberosity_centre, g.tuberosity_radius))
    tibia = fuse([plateau, tibia_shaft, tuberosity])
    px, py, pz = g.patella_centre
    patella = [(3, occ.addSphere(px, py, pz, 1.0))]
    occ.dilate(patella, px, py, pz, *g.patella_semi_axes)
    patella_recess = []
    if g.patella_recess > 0.0:
        # the patella's lower half dilated and swept back into the femur's clearance
        # (the femur takes precedence): a rounder recess left thin wedges of tissue, all four
        # vertices on the boundary, between its rim and the femur. Built round a unit sphere
        # and then dilated: OCC's booleans failed on the dilated (B-spline) shapes.
        a, b, c = (s + g.patella_recess for s in g.patella_semi_axes)
        sweep = (b + g.patella_recess_depth) / b
        unit = fuse([(3, occ.addSphere(px, py, pz, 1.0)),
                     (3, occ.addCylinder(px, py - sweep, pz, 0.0, sweep, 0.0, 1.0))])  # fmt: skip
        # cut off above patella_recess_top (through the equator exactly, the mesher met
        # intersecting facets)
        top = g.patella_recess_top / c
        above = (3, occ.addBox(px - 2, py - 2 - sweep, pz + top, 4, 4 + sweep, 2))
        patella_recess = cut(unit, [above])
        occ.dilate(patella_recess, px, py, pz, a, b, c)
    if g.fat_pad_half_width > 0.0:
        y0, y1 = g.fat_pad_y
        z0, z1 = g.plateau_top, pz - 12.0
        w = g.fat_pad_half_width
        patella_recess.append((3, occ.addBox(-w, y0, z0, 2 * w, y1 - y0, z1 - z0)))

    # -- tendon and ligament, glued to the bones they join
    tendon_bottom = pz + 0.5 * g.patella_semi_axes[2]
    tendon = [
        ellipse_cylinder(0.0, py, tendon_bottom, g.tendon_length + pz + g.patella_semi_axes[2]
                         - tendon_bottom, *g.tendon_semi_axes)
    ]  # fmt: skip
    top, bottom = g.ligament_ends
    axis = bottom - top
    length = float(np.linalg.norm(axis))
    ligament = [ellipse_cylinder(*top, length, *g.ligament_semi_axes)]
    # a rotation by t about x takes (0, 0, 1) to (0, -sin t, cos t)
    occ.rotate(ligament, *top, 1.0, 0.0, 0.0, math.atan2(-axis[1], axis[2]))

    # -- envelope: skin surface, skin-fat layer, crease
    def envelope(inset):
        thigh_cone = (
            3,
            occ.addCone(0.0, 0.0, g.knee_level, 0.0, 0.0, g.thigh_length - g.knee_level,
                        g.knee_radius - inset, g.thigh_radius - inset),
        )  # fmt: skip
        shank_cone = (
            3,
            occ.addCone(0.0, 0.0, -g.shank_length, 0.0, 0.0, g.knee_level + g.shank_length,
                        g.ankle_radius - inset, g.knee_radius - inset),
        )  # fmt: skip
        # the crease: a slot with a rounded bottom, drawn in the y-z plane and extruded along x
        back = -g.outer_radius(g.crease_level) - 10.0
        floor = -g.outer_radius(g.crease_level) + g.fossa_depth
        centre = floor + g.crease_depth - g.crease_half_width
        w = g.crease_half_width + inset
        half = g.crease_half_length + inset
        z = g.crease_level
        p = [
            occ.addPoint(-half, yy, zz)
            for yy, zz in ((back, z - w), (centre, z - w), (centre + w, z), (centre, z + w),
                           (back, z + w), (centre, z))
        ]  # fmt: skip
        curves = [
            occ.addLine(p[0], p[1]),
            occ.addCircleArc(p[1], p[5], p[2]),
            occ.addCircleArc(p[2], p[5], p[3]),
            occ.addLine(p[3], p[4]),
            occ.addLine(p[4], p[0]),
        ]
        slot = extrude_face(curves, 2 * half, 0.0, 0.0)
        # the popliteal fossa: a cylinder along x whose front touches the fossa's floor
        fossa = (
            3,
            occ.addCylinder(-100.0, floor - g.fossa_radius, z, 200.0, 0.0, 0.0,
                            g.fossa_radius + inset),
        )  # fmt: skip
        return cut(fuse([thigh_cone, shank_cone]), [slot, fossa])

    outer = envelope(0.0)
    inner = envelope(g.skin)

    # -- sliding gaps: a clearance around the distal femur and the joint space
    clearance = femur_shape(g.gap)
    # the thigh tissue is glued to the femoral shaft behind it, above the condyles
    attachment = (3, occ.addBox(-100, -100, g.attachment_level, 200, 100 + g.femur_shaft_offset,
                                g.thigh_length + 20))  # fmt: skip
    clearance = cut(clearance, [attachment])
    # the cavity between condyles and plateau, inside the plateau's rim
    joint_space = ellipse_cylinder(
        0.0, g.joint_space_offset, z_plateau, g.joint_space_top - z_plateau,
        *g.joint_space_semi_axes,
    )  # fmt: skip
    cavity = fuse([*clearance, joint_space])
    popliteal = []
    if g.popliteal_space_half_width > 0.0:
        # drawn in the y-z plane at x = -w and extruded along x
        w = g.popliteal_space_half_width
        corners = g.popliteal_space_outline
        points = [occ.addPoint(-w, y, z) for y, z in corners]
        lines = [occ.addLine(points[i], points[(i + 1) % len(points)]) for i in range(len(points))]
        popliteal = [extrude_face(lines, 2 * w, 0.0, 0.0)]
    quad_box = (3, occ.addBox(-100, g.femur_shaft_offset, g.quadriceps_start, 200, 100, 200))
    thigh_box = (3, occ.addBox(-100, -100, 0.0, 200, 200, 200))

    # -- one fragment of the overlapping shapes; each piece goes to the first body (in this
    # order of priority) whose shapes contain it. Pieces outside the skin surface, and the
    # gaps, are removed. Robuster than cutting each body out of the others beforehand
    # (coincident curved faces make OCC's booleans fail).
    shapes = {
        "femur": femur,
        "tibia": tibia,
        "patella": patella,
        "cavity": cavity,
        "tendon": tendon,
        "ligament": ligament,
        "patella_recess": patella_recess,  # and the fat pad's box
        "popliteal": popliteal,
        "outer": outer,
        "inner": inner,
        "quad_box": [quad_box],
        "thigh_box": [thigh_box],
    }
    inputs = [dt for dts in shapes.values() for dt in dts]
    owner = [name for name, dts in shapes.items() for _ in dts]
    _, pieces = occ.fragment(inputs, [])
    occ.synchronize()
    parents: dict[int, set[str]] = {}
    for name, children in zip(owner, pieces, strict=True):
        for d, t in children:
            if d == 3:
                parents.setdefault(t, set()).add(name)

    def classify(names: set[str]) -> int | None:
        if "outer" not in names:
            return None  # outside the leg
        for name, tag in (("femur", FEMUR), ("tibia", TIBIA), ("patella", PATELLA)):
            if name in names:
                return tag
        if "cavity" in names or ("popliteal" in names and "inner" in names):
            return None
        for name, tag in (("tendon", TENDON), ("ligament", LIGAMENT)):
            if name in names:
                return tag
        if "patella_recess" in names:
            return None
        if "inner" not in names:
            return SKIN
        if "quad_box" in names:
            return QUADRICEPS
        return THIGH if "thigh_box" in names else CALF

    volumes: dict[int, list[int]] = {tag: [] for tag in BODIES}
    removed = []
    for volume, names in parents.items():
        tag = classify(names)
        if tag is None:
            removed.append((3, volume))
        else:
            volumes[tag].append(volume)
    occ.remove(removed, recursive=True)
    occ.synchronize()
    for tag, vols in volumes.items():
        if not vols:
            raise RuntimeError(f"leg geometry: body {BODIES[tag]} is empty")
        gmsh_model.addPhysicalGroup(3, sorted(vols), tag, name=BODIES[tag])
    kept = [(3, v) for vols in volumes.values() for v in vols]

    tol = 1e-3
    cuts = {PROXIMAL_CUT: [], DISTAL_CUT: []}
    for dim, tag in gmsh_model.getEntities(2):
        _, _, z0, _, _, z1 = gmsh_model.getBoundingBox(dim, tag)
        if abs(z0 - g.thigh_length) < tol and abs(z1 - g.thigh_length) < tol:
            cuts[PROXIMAL_CUT].append(tag)
        elif abs(z0 + g.shank_length) < tol and abs(z1 + g.shank_length) < tol:
            cuts[DISTAL_CUT].append(tag)
    gmsh_model.addPhysicalGroup(2, cuts[PROXIMAL_CUT], PROXIMAL_CUT, name="proximal_cut")
    gmsh_model.addPhysicalGroup(2, cuts[DISTAL_CUT], DISTAL_CUT, name="distal_cut")

    # -- mesh sizes: fine near the skin surface and on the sliding surfaces, coarse inside
    exterior = gmsh_model.getBoundary(kept, combined=True, oriented=False)
    field = gmsh_model.mesh.field
    distance = field.add("Distance")
    field.setNumbers(distance, "SurfacesList", [t for d, t in exterior if d == 2])
    field.setNumber(distance, "Sampling", 40)
    threshold = field.add("Threshold")
    field.setNumber(threshold, "InField", distance)
    field.setNumber(threshold, "SizeMin", h_surface)
    field.setNumber(threshold, "SizeMax", h_interior)
    field.setNumber(threshold, "DistMin", g.skin)
    field.setNumber(threshold, "DistMax", g.skin + 15.0)
    field.setAsBackgroundMesh(threshold)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    # curved sliding surfaces: fine enough that chords do not cross the gap
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", per_turn)
    gmsh.option.setNumber("Mesh.MeshSizeMax", h_interior)
    gmsh.option.setNumber("General.NumThreads", 1)  # the same mesh on every run
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)
    gmsh.option.setNumber("Mesh.OptimizeThreshold", 0.45)
    gmsh_model.mesh.generate(3)
    gmsh_model.mesh.optimize("", niter=3)
    gmsh_model.mesh.optimize("Relocate3D")


def leg_mesh(
    comm: MPI.Comm = MPI.COMM_WORLD,
    resolution: float | str = "default",
    geometry: LegGeometry | None = None,
) -> tuple[dolfinx.mesh.Mesh, dolfinx.mesh.MeshTags, dolfinx.mesh.MeshTags]:
    """The leg meshed by gmsh on rank 0 and distributed over ``comm`` (collective).

    Args:
        comm: MPI communicator of the mesh.
        resolution: see :func:`build_leg_model`.
        geometry: dimensions; default :class:`LegGeometry()`.

    Returns:
        ``(mesh, cell_tags, facet_tags)`` with the tags of this module.
    """
    return gmsh_build_to_mesh(lambda model: build_leg_model(model, geometry, resolution), comm)


def mesh_statistics(mesh: dolfinx.mesh.Mesh) -> dict[str, float]:
    """Counts and quality figures of a tetrahedral mesh (collective).

    Returns:
        ``vertices``, ``tetrahedra``, ``boundary_triangles`` (exterior facets),
        ``zero_depth_tetrahedra`` (tetrahedra whose four vertices all lie on the exterior
        boundary: material depth zero throughout, so nothing that enters them is pushed back),
        ``min_volume`` and ``max_volume`` (mm^3; a non-positive volume is an inverted element)
        and ``min_edge``, ``median_edge`` (mm).
    """
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    n_facets_owned = mesh.topology.index_map(tdim - 1).size_local
    owned_facets = facets[facets < n_facets_owned]
    on_boundary = np.zeros(
        mesh.topology.index_map(0).size_local + mesh.topology.index_map(0).num_ghosts, dtype=bool
    )
    mesh.topology.create_connectivity(tdim - 1, 0)
    f2v = mesh.topology.connectivity(tdim - 1, 0)
    for f in facets:
        on_boundary[f2v.links(f)] = True
    # a vertex on the boundary of another rank's facets only: share the flags
    imap = mesh.topology.index_map(0)
    flags = dolfinx.la.vector(imap, 1, dtype=np.int32)
    flags.array[:] = on_boundary.astype(np.int32)
    flags.scatter_reverse(dolfinx.la.InsertMode.add)
    flags.scatter_forward()
    on_boundary = flags.array > 0
    n_cells = mesh.topology.index_map(tdim).size_local
    c2v = mesh.topology.connectivity(tdim, 0)
    cells = np.asarray(c2v.array).reshape(-1, 4)[:n_cells]
    zero_depth = int(np.count_nonzero(np.all(on_boundary[cells], axis=1)))
    nodes = np.asarray(dolfinx.mesh.entities_to_geometry(mesh, tdim, np.arange(n_cells), False))
    x = mesh.geometry.x[nodes]
    volume = np.einsum(
        "ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]
    )
    volume /= 6.0
    edges = np.linalg.norm(x[:, [1, 2, 3, 2, 3, 3]] - x[:, [0, 0, 0, 1, 1, 2]], axis=2)
    comm = mesh.comm
    all_edges = np.concatenate(comm.allgather(edges.ravel()))
    return {
        "vertices": imap.size_global,
        "tetrahedra": mesh.topology.index_map(tdim).size_global,
        "boundary_triangles": comm.allreduce(int(owned_facets.size)),
        "zero_depth_tetrahedra": comm.allreduce(zero_depth),
        "min_volume": comm.allreduce(float(np.min(np.abs(volume))), op=MPI.MIN),
        "inverted": comm.allreduce(int(np.count_nonzero(volume <= 0.0))),
        "max_volume": comm.allreduce(float(np.max(np.abs(volume))), op=MPI.MAX),
        "min_edge": float(all_edges.min()),
        "median_edge": float(np.median(all_edges)),
    }


if __name__ == "__main__":
    import argparse
    from pathlib import Path

    from dolfinx.io import XDMFFile

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--resolution", default="default", help="coarse, default, fine or a scale")
    args = parser.parse_args()
    resolution = args.resolution if args.resolution in RESOLUTIONS else float(args.resolution)
    mesh, cell_tags, facet_tags = leg_mesh(MPI.COMM_WORLD, resolution)
    stats = mesh_statistics(mesh)
    if MPI.COMM_WORLD.rank == 0:
        print(
            f"leg mesh ({args.resolution}): " + ", ".join(f"{k} {v:.4g}" for k, v in stats.items())
        )
    out = Path(__file__).resolve().parents[1] / "output"
    out.mkdir(exist_ok=True)
    with XDMFFile(mesh.comm, out / "leg.xdmf", "w") as xdmf:
        xdmf.write_mesh(mesh)
        mesh.topology.create_connectivity(2, 3)
        xdmf.write_meshtags(cell_tags, mesh.geometry)
        xdmf.write_meshtags(facet_tags, mesh.geometry)
