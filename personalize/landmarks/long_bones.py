"""Long-bone axes: the shaft and end blocks of a femur or tibia from its surface alone.

The long axis is the largest principal axis; each end is characterised by the
spread of its block and whether it is a planar field-of-view cut
(`long_bone_axes`); `shaft_line` fits the diaphysis centre line.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lowerlimb.geometry import orient

from .shape_fits import principal_axes
from .surface import Surface

__all__ = ["LongBoneAxes", "long_bone_axes", "shaft_line"]


@dataclass(frozen=True)
class LongBoneAxes:
    """Long axis of a bone and what its two ends look like.

    ``axis`` points towards end ``+1``; ``h`` is each vertex's height along it
    from ``centre``; ``flatness[e]`` is the ratio of the smaller to the larger
    cross-sectional spread of the end region ``e`` (``+1`` / ``-1``),
    ``area[e]`` its surface area and ``cut[e]`` whether the end is a planar
    cut (truncated by the field of view).
    """

    centre: np.ndarray
    axis: np.ndarray
    h: np.ndarray
    length: float
    flatness: dict
    area: dict
    cut: dict
    shaft_radius: float


def long_bone_axes(surface: Surface, end_fraction: float = 0.2, end_max: float = 0.08) -> LongBoneAxes:
    """Principal long axis and end descriptors of a long bone (femur, tibia)."""
    V, A, Nrm = surface.vertices, surface.areas, surface.normals
    c, ax, _ = principal_axes(V, A)
    e = ax[:, 0]
    h = (V - c) @ e
    L = float(h.max() - h.min())
    mid = np.abs(h - 0.5 * (h.max() + h.min())) < 0.1 * L
    if mid.sum() > 10:
        cm = (A[mid] @ V[mid]) / A[mid].sum()
        d = V[mid] - cm
        d -= np.outer(d @ e, e)
        r_shaft = float(np.median(np.linalg.norm(d, axis=1)))
    else:
        r_shaft = 0.1 * L
    flat, area, cut = {}, {}, {}
    depth = min(end_fraction * L, end_max)
    for sgn in (1, -1):
        hh = sgn * h
        top = hh > hh.max() - depth
        _, _, sd2 = principal_axes(V[top] - np.outer((V[top] - c) @ e, e), A[top])
        flat[sgn] = float(sd2[1] / max(sd2[0], 1e-12))
        area[sgn] = float(A[top].sum())
        cut[sgn] = _is_cut(V, Nrm, A, hh, sgn * e, r_shaft)
    return LongBoneAxes(centre=c, axis=e, h=h, length=L, flatness=flat, area=area, cut=cut, shaft_radius=r_shaft)


def shaft_line(surface: Surface, axis: np.ndarray, h: np.ndarray, lo: float, hi: float, n_slices: int = 9):
    """Line through the area centroids of slices ``lo < h < hi`` (m along ``axis``).

    Returns ``(point, direction)`` with the direction oriented along ``axis``.
    """
    V, A = surface.vertices, surface.areas
    edges = np.linspace(lo, hi, n_slices + 1)
    cents = []
    for a, b in zip(edges[:-1], edges[1:]):
        m = (h >= a) & (h < b)
        if m.sum() >= 6:
            cents.append((A[m] @ V[m]) / A[m].sum())
    cents = np.array(cents)
    if len(cents) < 3:
        m = (h >= lo) & (h <= hi)
        c, ax, _ = principal_axes(V[m], A[m])
        return c, orient(ax[:, 0], axis)
    c, ax, _ = principal_axes(cents)
    return c, orient(ax[:, 0], axis)


def _is_cut(V, Nrm, A, hh, direction, r_shaft) -> bool:
    """Whether the end of a long bone at the top of ``hh`` is a planar cut.

    A field-of-view cut leaves a flat cap (normals along the axis, coplanar
    within 0.5 mm) nearly as wide as the bone just below it (at least a third
    of the convex cross-section 8 mm below the tip, the rest being the rim
    rounded by surface smoothing), and below it the sides run along the axis
    (mean |n.axis| < 0.68 between 3 and 8 mm below the tip, rounded rim
    included).  A rounded epiphysis, even with a flat staircase patch at its
    top (slice-thick MRI), keeps a small top patch (< 30 % of that section)
    and turns gradually (mean |n.axis| >= 0.7 there).
    """
    from scipy.spatial import ConvexHull, QhullError

    tip = hh > hh.max() - 0.004
    cosn = Nrm @ direction
    flat = tip & (cosn > 0.95)
    if flat.sum() < 10 or A[flat].sum() < 0.25 * np.pi * r_shaft ** 2:
        return False
    _, _, qsd = principal_axes(V[flat], A[flat])
    if qsd[2] > 0.0005:
        return False
    slab = np.abs(hh - (hh.max() - 0.008)) < 0.001
    if slab.sum() < 8:
        return False
    u = np.cross(direction, [1.0, 0.0, 0.0])
    if np.linalg.norm(u) < 0.1:
        u = np.cross(direction, [0.0, 1.0, 0.0])
    u = u / np.linalg.norm(u)
    w = np.cross(direction, u)
    Q = np.column_stack([V[slab] @ u, V[slab] @ w])
    try:
        sec = ConvexHull(Q).volume                 # area in 2-D
    except QhullError:
        return False
    # below a cut the bone's sides run along the axis (a smoothed rim aside);
    # below a rounded end they turn gradually
    band = (hh < hh.max() - 0.003) & (hh > hh.max() - 0.008)
    if not band.any():
        return False
    side_cos = float(A[band] @ np.abs(cosn[band]) / A[band].sum())
    return bool(A[flat].sum() > 0.33 * sec and side_cos < 0.68)
