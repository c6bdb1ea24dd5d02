"""Which body of the model each static marker rides on (`SubjectParameters.marker_bodies`).

Every marker of the static trial is kept in the model under its own label:
on the segment the marker set gives it, or, for a marker the set leaves out,
on the body whose registered bone surface is nearest in the static trial
(nearest vertex of the bone meshes moved into the lab by their segment's
registration; `pipeline.model.bone_meshes_lab`).  Markers the set puts on
``torso`` or ``ignore``, markers of a side the model does not have, and
markers never seen in the static trial are not placed, and the summary says
why.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kinematics.io.marker_sets import SPECIAL_SEGMENTS

__all__ = ["MarkerAssignment", "assign_markers", "model_markers"]


@dataclass(frozen=True)
class MarkerAssignment:
    """bodies : label -> body; how : label -> "marker set" or "nearest bone";
    nearest : label -> {body: distance m} of the bones nearest a marker the set leaves out (nearest first);
    not_placed : label -> why the marker is not on the model"""

    bodies: dict
    how: dict
    nearest: dict = field(default_factory=dict)
    not_placed: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """summary.json ``markers``: per marker its body and why; distances in mm."""
        placed = {}
        for k in sorted(self.bodies):
            e = {"body": self.bodies[k], "from": self.how[k]}
            if k in self.nearest:
                e["nearest_bones_mm"] = {b: round(d * 1e3, 1) for b, d in self.nearest[k].items()}
            placed[k] = e
        return {"units": "mm", "placed": placed, "not_placed": dict(sorted(self.not_placed.items()))}


def _nearest_bodies(x: np.ndarray, meshes_lab: dict, n: int = 3) -> dict:
    """body -> distance (m) from `x` to the nearest vertex of its bones, the `n` nearest bodies, nearest first."""
    from scipy.spatial import cKDTree

    best: dict = {}
    for bone, (mesh, body) in meshes_lab.items():
        V = np.asarray(mesh.vertices, float)
        if V.size == 0:
            continue
        d = float(cKDTree(V).query(x)[0])
        best[body] = min(best.get(body, np.inf), d)
    return dict(sorted(best.items(), key=lambda kv: kv[1])[:n])


def assign_markers(static: dict, marker_set, meshes_lab: dict, bodies) -> MarkerAssignment:
    """Body of every static marker (module docstring).

    Parameters
    ----------
    static : label -> (3,) median static position (static lab, m), the trial's own labels
    marker_set : `kinematics.io.marker_sets.MarkerSet` or None (every marker then by nearest bone)
    meshes_lab : bone -> (trimesh mesh in the static lab, body) (`pipeline.model.bone_meshes_lab`)
    bodies : names of the model's bodies

    Returns
    -------
    MarkerAssignment
    """
    bodies = set(bodies)
    out, how, nearest, skipped = {}, {}, {}, {}
    for label, x in static.items():
        x = np.asarray(x, float)
        md = marker_set.markers.get(label) if marker_set is not None else None
        if md is not None and md.segment in SPECIAL_SEGMENTS:
            skipped[label] = f"segment {md.segment} in the marker set (not a body of the lower-limb model)"
            continue
        if not np.all(np.isfinite(x)):
            skipped[label] = "never visible in the static trial"
            continue
        if md is not None:
            if md.segment in bodies:
                out[label], how[label] = md.segment, "marker set"
            else:
                skipped[label] = f"its segment {md.segment} is not in the model (side without bones or markers)"
            continue
        near = _nearest_bodies(x, {k: v for k, v in meshes_lab.items() if v[1] in bodies})
        if not near:
            skipped[label] = "left out of the marker set and no registered bone to assign it to"
            continue
        nearest[label] = near
        out[label], how[label] = next(iter(near)), "nearest bone"
    return MarkerAssignment(out, how, nearest, skipped)


def model_markers(inputs, meshes_lab: dict) -> MarkerAssignment:
    """`assign_markers` of a subject (`personalize.pipeline.SubjectInputs`): its static trial's markers (median
    positions), its marker set, the bodies of its sides."""
    from ..registration import static_marker_positions

    bodies = ["pelvis"] + [f"{b}_{s}" for s in inputs.sides for b in ("femur", "tibia", "talus", "calcn", "toes")]
    static = {n: g.mean for n, g in static_marker_positions(inputs.static).items()}
    return assign_markers(static, inputs.marker_set, meshes_lab, bodies)
