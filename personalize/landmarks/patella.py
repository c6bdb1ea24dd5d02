"""Patella: centre and articular-surface frame.

Centre = centroid of the enclosed volume (surface centroid for open meshes).
Frame (X anterior, Y superior, Z right): X is the patella's thinnest
principal axis, pointing away from the femur (the articular surface faces the
trochlea); Y is the femur's proximal direction projected onto the patellar
plane; Z = X x Y.  Without a femur the frame is built from the principal axes
and flagged low-confidence.
"""
from __future__ import annotations

import numpy as np

from lowerlimb.geometry import unit
from lowerlimb.bones import side_of

from .common import FLAG_LOW_CONFIDENCE, BoneLandmarks, Landmark
from .shape_fits import perpendicular, principal_axes
from .surface import Surface

__all__ = ["detect_patella"]


def _volume_centroid(s: Surface) -> np.ndarray:
    T = s.vertices[s.faces]
    v = np.einsum("ij,ij->i", T[:, 0], np.cross(T[:, 1], T[:, 2])) / 6.0
    if abs(v.sum()) < 1e-12:
        return (s.areas @ s.vertices) / s.areas.sum()
    return (v[:, None] * T.sum(axis=1) / 4.0).sum(axis=0) / v.sum()


def detect_patella(surface: Surface, name: str = "patella_r", *, femur: Surface | None = None,
                   proximal_hint=None) -> BoneLandmarks:
    res = BoneLandmarks(bone=name, side=side_of(name))
    c = _volume_centroid(surface) if surface.closed else (surface.areas @ surface.vertices) / surface.areas.sum()
    _, ax, sd = principal_axes(surface.vertices, surface.areas)
    res.landmarks["patella_centre"] = Landmark(c, (0.0005 ** 2) * np.eye(3))
    X = ax[:, 2]
    if femur is not None:
        _, j = femur.tree().query(c)
        X = X if (c - femur.vertices[j]) @ X > 0 else -X
    else:
        res.flag(FLAG_LOW_CONFIDENCE, "patella without femur: anterior direction unknown")
    if proximal_hint is not None:
        Y = unit(perpendicular(np.asarray(proximal_hint, float), X))
    else:
        Y = ax[:, 0]
        res.flag(FLAG_LOW_CONFIDENCE, "patella superior direction from its principal axis only")
    Z = np.cross(X, Y)
    res.frames["articular"] = {"origin": c.copy(), "rotation": np.column_stack([X, Y, Z])}
    return res
