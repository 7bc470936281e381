"""Mass model of the body and the object.

Body: total mass from the fitted rest mesh's volume times a tissue density (the mesh must be
watertight), unless the session gives `body: {mass_kg: ...}`. That mass is split into segments
by an anthropometric table after de Leva (1996, "Adjustments to Zatsiorsky-Seluyanov's segment
inertia parameters", Table 4): per segment its mass fraction, the position of its centre of
mass between two endpoints (fraction of the segment length from the first endpoint) and its
radii of gyration about the sagittal, transverse and longitudinal axes (fractions of the
length). Each segment's endpoints are named by the body model's bones (bone heads) or by mesh
vertices (head top, heel, toe tip), and the segment moves with one bone of the model (its
"carrier": fingers belong to the hand, toes to the foot, so their mass rides on the wrist and
foot bones). Male and female tables are blended by the fitted phenotype (anny's `gender`,
0 = male, 1 = female) or chosen in the config.

Object: `object.mass_kg`, else mesh volume x `object.density_kg_m3`, else unknown (NaN: the
stage then skips the object's forces and says so; no mass is invented).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TISSUE_DENSITY = 1010.0  # kg/m^3, whole-body average

# de Leva (1996) Table 4, checked against the published table: per segment (mass % of body mass,
# CM % of the segment length from the first endpoint, radii of gyration % of the length about the
# sagittal, transverse and longitudinal axes). The rows are the table's alternatives whose endpoints
# the body model has: head and upper trunk from cervicale (C7), the shank from the knee to the ankle
# joint centre (not the lateral malleolus). The female masses sum to 99.99 % as published
# (rounding); de_leva_table renormalises them to exactly 1.
DE_LEVA_MALE = {
    "head": (6.94, 50.02, 30.3, 31.5, 26.1),  # vertex -> cervicale (C7)
    "upper_trunk": (15.96, 50.66, 50.5, 32.0, 46.5),  # cervicale -> xiphoid
    "mid_trunk": (16.33, 45.02, 48.2, 38.3, 46.8),  # xiphoid -> omphalion
    "lower_trunk": (11.17, 61.15, 61.5, 55.1, 58.7),  # omphalion -> mid hip joint centres
    "upper_arm": (2.71, 57.72, 28.5, 26.9, 15.8),  # shoulder -> elbow joint centre
    "forearm": (1.62, 45.74, 27.6, 26.5, 12.1),  # elbow -> wrist joint centre
    "hand": (0.61, 79.00, 62.8, 51.3, 40.1),  # wrist -> third metacarpal head
    "thigh": (14.16, 40.95, 32.9, 32.9, 14.9),  # hip -> knee joint centre
    "shank": (4.33, 43.95, 25.1, 24.6, 10.2),  # knee joint centre -> ankle joint centre
    "foot": (1.37, 44.15, 25.7, 24.5, 12.4),  # heel -> toe tip
}
DE_LEVA_FEMALE = {
    "head": (6.68, 48.41, 27.1, 29.5, 26.1),
    "upper_trunk": (15.45, 50.50, 46.6, 31.4, 44.9),
    "mid_trunk": (14.65, 45.12, 43.3, 35.4, 41.5),
    "lower_trunk": (12.47, 49.20, 43.3, 40.2, 44.4),
    "upper_arm": (2.55, 57.54, 27.8, 26.0, 14.8),
    "forearm": (1.38, 45.59, 26.1, 25.7, 9.4),
    "hand": (0.56, 74.74, 53.1, 45.4, 33.5),
    "thigh": (14.78, 36.12, 36.9, 36.4, 16.2),
    "shank": (4.81, 43.52, 26.7, 26.3, 9.2),
    "foot": (1.29, 40.14, 29.9, 27.9, 13.9),
}

UNPAIRED = ("head", "upper_trunk", "mid_trunk", "lower_trunk")  # the other rows come left and right

# anny segments: (segment, table row, first endpoint, second endpoint, carrier bone). An endpoint is
# a bone name (its head), "mid:A:B" (midpoint of two bone heads) or "vertex:NAME" (a landmark vertex).
ANNY_SEGMENTS = [
    ("head", "head", "vertex:head_top", "neck01", "head"),
    ("upper_trunk", "upper_trunk", "neck01", "spine01", "spine01"),
    ("mid_trunk", "mid_trunk", "spine01", "spine03", "spine03"),
    ("lower_trunk", "lower_trunk", "spine03", "mid:upperleg01.L:upperleg01.R", "root"),
] + [
    row
    for s in ("L", "R")
    for row in (
        (f"upper_arm.{s}", "upper_arm", f"upperarm01.{s}", f"lowerarm01.{s}", f"upperarm01.{s}"),
        (f"forearm.{s}", "forearm", f"lowerarm01.{s}", f"wrist.{s}", f"lowerarm01.{s}"),
        (f"hand.{s}", "hand", f"wrist.{s}", f"finger3-1.{s}", f"wrist.{s}"),
        (f"thigh.{s}", "thigh", f"upperleg01.{s}", f"lowerleg01.{s}", f"upperleg01.{s}"),
        (f"shank.{s}", "shank", f"lowerleg01.{s}", f"foot.{s}", f"lowerleg01.{s}"),
        (f"foot.{s}", "foot", f"vertex:heel.{s}", f"vertex:toe_tip.{s}", f"foot.{s}"),
    )
]


class MassError(ValueError):
    """A mass cannot be determined (names the file or setting to fix)."""


def de_leva_table(female_fraction: float) -> dict[str, np.ndarray]:
    """The table blended between male (0) and female (1); rows as fractions (not %), the mass
    fractions of the whole body (both sides of the paired segments) summing to exactly 1."""
    w = float(np.clip(female_fraction, 0.0, 1.0))
    rows = {k: ((1 - w) * np.array(DE_LEVA_MALE[k]) + w * np.array(DE_LEVA_FEMALE[k])) / 100.0 for k in DE_LEVA_MALE}
    total = sum(r[0] * (1 if k in UNPAIRED else 2) for k, r in rows.items())
    for r in rows.values():
        r[0] /= total
    return rows


def mesh_volume(vertices: np.ndarray, faces: np.ndarray, what: str = "mesh") -> float:
    """Enclosed volume (m^3) of a closed triangle mesh; MassError when it is not watertight."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces), process=True)
    if not mesh.is_watertight:
        raise MassError(f"{what} is not watertight, so its volume (and mass) is undefined")
    return float(abs(mesh.volume))


def body_mass_from_volume(vertices: np.ndarray, faces: np.ndarray, density: float = TISSUE_DENSITY) -> float:
    """Body mass (kg) = rest mesh volume x density."""
    return mesh_volume(vertices, faces, "the fitted rest body mesh") * density


@dataclass
class SegmentModel:
    """Rigid segments of the body: everything Newton-Euler needs, in the model's rest frame.

    Per segment s: mass (S,) kg, carrier (S,) bone index, endpoints (S, 2) point specs,
    com_fraction (S,) of the way from the first to the second endpoint, inertia_rest (S, 3, 3)
    kg m^2 about the COM in rest model coordinates, carrier_rest (S, 3, 3) the carrier bone's rest
    orientation (the inertia turns with the carrier: I(t) = Q I_rest Q^T, Q = R_bone(t) R_rest^T)."""

    names: list[str]
    mass: np.ndarray
    carrier: np.ndarray
    endpoints: list[tuple[str, str]]
    com_fraction: np.ndarray
    inertia_rest: np.ndarray
    carrier_rest: np.ndarray

    @property
    def total_mass(self) -> float:
        return float(self.mass.sum())


def segment_inertia(mass: float, length: float, radii: np.ndarray, axis: np.ndarray, lateral: np.ndarray) -> np.ndarray:
    """(3, 3) inertia about the COM: radii (sagittal, transverse, longitudinal) x length, the
    longitudinal axis along `axis`, the transverse one along `lateral` made orthogonal to it."""
    long = axis / np.linalg.norm(axis)
    trans = lateral - (lateral @ long) * long
    trans /= np.linalg.norm(trans)
    sag = np.cross(long, trans)
    E = np.stack([sag, trans, long], 1)  # (3, 3) columns: principal axes
    moments = mass * (np.asarray(radii) * length) ** 2
    return E @ np.diag(moments) @ E.T


def build_segments(bone_names: list[str], rest_heads: np.ndarray, rest_rotations: np.ndarray,
                   landmarks: dict[str, np.ndarray], total_mass: float, female_fraction: float,
                   lateral: np.ndarray, segments=ANNY_SEGMENTS) -> SegmentModel:
    """Segment masses, COM positions and inertias of a body of `total_mass` kg from its rest pose:
    bone heads (J, 3) and orientations (J, 3, 3), landmark points by name, the model's lateral axis."""
    index = {b: i for i, b in enumerate(bone_names)}
    table = de_leva_table(female_fraction)
    missing = [b for row in segments for b in (row[4],) if b not in index]
    if missing:
        raise MassError(f"the body model lacks the bones {missing} the segment table needs")

    def point(spec: str) -> np.ndarray:
        return resolve_points(spec, index, rest_heads[None], {k: v[None] for k, v in landmarks.items()})[0]

    names, mass, carrier, ends, frac, inertia, rest_R = [], [], [], [], [], [], []
    for name, row, a, b, bone in segments:
        m_frac, cm, r_sag, r_trans, r_long = table[row]
        pa, pb = point(a), point(b)
        length = float(np.linalg.norm(pb - pa))
        m = m_frac * total_mass
        names.append(name)
        mass.append(m)
        carrier.append(index[bone])
        ends.append((a, b))
        frac.append(cm)
        inertia.append(segment_inertia(m, length, np.array([r_sag, r_trans, r_long]), pb - pa, lateral))
        rest_R.append(rest_rotations[index[bone]])
    return SegmentModel(names, np.array(mass), np.array(carrier), ends, np.array(frac), np.array(inertia),
                        np.array(rest_R))


def resolve_points(spec: str, index: dict[str, int], heads: np.ndarray, landmarks: dict[str, np.ndarray]) -> np.ndarray:
    """(T, 3) positions of one endpoint spec from bone heads (T, J, 3) and landmarks (T, 3) each."""
    if spec.startswith("vertex:"):
        return landmarks[spec[7:]]
    if spec.startswith("mid:"):
        _, a, b = spec.split(":")
        return 0.5 * (heads[:, index[a]] + heads[:, index[b]])
    return heads[:, index[spec]]


def segment_coms(model: SegmentModel, index: dict[str, int], heads: np.ndarray, landmarks: dict[str, np.ndarray]) -> np.ndarray:
    """(T, S, 3) world centres of mass of the segments from posed bone heads (T, J, 3) and landmarks."""
    out = []
    for (a, b), f in zip(model.endpoints, model.com_fraction):
        pa, pb = resolve_points(a, index, heads, landmarks), resolve_points(b, index, heads, landmarks)
        out.append(pa + f * (pb - pa))
    return np.stack(out, 1)


def object_mass(mass_kg: float | None, density_kg_m3: float | None, vertices, faces) -> tuple[float, str]:
    """(kg, how it was found): the given mass, else volume x density, else (NaN, why unknown)."""
    if mass_kg is not None:
        return float(mass_kg), "session.yaml object.mass_kg"
    if density_kg_m3 is not None:
        try:
            return mesh_volume(vertices, faces, "the object mesh") * float(density_kg_m3), "mesh volume x object.density_kg_m3"
        except MassError as exc:
            return float("nan"), f"unknown: {exc}; give object.mass_kg in session.yaml"
    return float("nan"), "unknown: session.yaml gives neither object.mass_kg nor object.density_kg_m3"


def object_inertia(vertices, faces, mass: float) -> tuple[np.ndarray, np.ndarray]:
    """(centre of mass (3,), inertia (3, 3) about it) in object coordinates for a uniform solid of
    `mass`; a mesh that is not watertight gets its bounding box's."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces), process=True)
    if mesh.is_watertight and abs(mesh.volume) > 1e-12:
        if mesh.volume < 0:
            mesh.invert()
        props = mesh.mass_properties
        scale = mass / props["mass"]
        return np.asarray(props["center_mass"]), np.asarray(props["inertia"]) * scale
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    d = hi - lo
    box = mass / 12.0 * np.diag([d[1] ** 2 + d[2] ** 2, d[0] ** 2 + d[2] ** 2, d[0] ** 2 + d[1] ** 2])
    return (lo + hi) / 2, box
