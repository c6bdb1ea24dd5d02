"""Rigid segment poses from marker clusters (Söderkvist & Wedin 1993).

Model: each measured marker b_fm = R_f a_m + t_f + ε, with a_m the marker in
the segment (reference) frame.  For every frame f the pose minimises the
weighted squared residual

    Σ_m w_m ‖R_f a_m + t_f - b_fm‖²,   R_f ∈ SO(3),

solved in closed form by the SVD of the weighted cross-covariance
H = Σ_m w_m (a_m - ā)(b_fm - b̄)ᵀ = U S Vᵀ:  R_f = V diag(1, 1, det(V Uᵀ)) Uᵀ,
t_f = b̄ - R_f ā (ā, b̄ weighted centroids).  Markers missing in a frame (NaN)
get weight 0 there; frames with fewer than 3 markers, or whose markers are
nearly collinear, get NaN.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lowerlimb.errors import FitError, InputError
from lowerlimb.geometry import kabsch_rotation

__all__ = ["RigidPose", "rigid_pose", "cluster_reference"]


@dataclass(frozen=True)
class RigidPose:
    """Per-frame rigid poses; unpacks as ``R, t, rms = rigid_pose(...)``.

    R : (F, 3, 3) rotation segment -> lab
    t : (F, 3) m, segment origin in the lab
    rms : (F,) m, weighted rms marker residual (NaN where no pose)
    n_markers : (F,) int, markers used per frame
    """

    R: np.ndarray
    t: np.ndarray
    rms: np.ndarray
    n_markers: np.ndarray

    def __iter__(self):
        return iter((self.R, self.t, self.rms))

    def to_lab(self, local: np.ndarray) -> np.ndarray:
        """Lab positions (F, 3) of a segment-fixed point (3,)."""
        return np.einsum("fij,j->fi", self.R, np.asarray(local, float)) + self.t

    def to_local(self, lab: np.ndarray) -> np.ndarray:
        """Segment coordinates of lab points (F, 3) or (F, K, 3)."""
        lab = np.asarray(lab, float)
        if lab.ndim == 2:
            return np.einsum("fji,fj->fi", self.R, lab - self.t)
        return np.einsum("fji,fkj->fki", self.R, lab - self.t[:, None])


def rigid_pose(reference: np.ndarray, measured: np.ndarray, weights: np.ndarray | None = None,
               *, min_spread: float = 1e-3) -> RigidPose:
    """Weighted least-squares rigid pose of a marker cluster in every frame.

    Parameters
    ----------
    reference : (M, 3) m, marker positions in the segment frame, M >= 3
    measured : (F, M, 3) m, lab positions, NaN where missing
    weights : (M,) non-negative, default all 1
    min_spread : m
        Frames whose second-largest principal spread of the used markers is
        below this (collinear cluster) get NaN.

    Returns
    -------
    RigidPose
    """
    a = np.asarray(reference, float)
    b = np.asarray(measured, float)
    if b.ndim == 2:
        b = b[None]
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 3 or b.shape[1:] != a.shape:
        raise InputError("rigid_pose", f"reference (M>=3, 3) and measured (F, M, 3) do not match: {a.shape} vs {b.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError("rigid_pose", "reference marker positions contain NaN")
    w = np.ones(a.shape[0]) if weights is None else np.asarray(weights, float)
    if w.shape != (a.shape[0],) or np.any(w < 0) or not np.any(w > 0):
        raise InputError("rigid_pose", "weights must be M non-negative numbers, not all zero")
    ok = np.all(np.isfinite(b), axis=2) & (w > 0)  # (F, M)
    W = np.where(ok, w, 0.0)
    n = ok.sum(axis=1)
    sw = W.sum(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        a_bar = (W @ a) / sw  # (F, 3)
        b0 = np.where(ok[..., None], b, 0.0)
        b_bar = np.einsum("fm,fmk->fk", W, b0) / sw
    ac = a[None] - a_bar[:, None]  # (F, M, 3)
    bc = np.where(ok[..., None], b0 - b_bar[:, None], 0.0)
    H = np.einsum("fm,fmi,fmj->fij", W, ac, bc)
    good = (n >= 3) & np.all(np.isfinite(H), axis=(1, 2))
    H = np.where(good[:, None, None], H, np.eye(3))
    R, _ = kabsch_rotation(H)
    t = b_bar - np.einsum("fij,fj->fi", R, a_bar)
    # Collinear clusters leave the rotation about their line undetermined.
    cov_a = np.einsum("fm,fmi,fmj->fij", W, ac, ac) / np.where(sw > 0, sw, 1.0)[..., None]
    spread = np.sqrt(np.clip(np.linalg.eigvalsh(cov_a)[:, 1], 0, None))
    good &= spread > min_spread
    res = np.einsum("fij,mj->fmi", R, a) + t[:, None] - b0
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.einsum("fm,fm->f", W, np.sum(res**2, axis=2)) / sw[:, 0])
    R[~good] = np.nan
    t[~good] = np.nan
    rms[~good] = np.nan
    return RigidPose(R, t, rms, n)


def cluster_reference(measured: np.ndarray, *, n_iter: int = 5) -> np.ndarray:
    """Mean cluster shape (M, 3) in its own centroid frame from a trial (F, M, 3).

    Generalised Procrustes: start from the frame with most markers, align
    every frame to the current shape with `rigid_pose`, average the aligned
    markers (ignoring NaN), repeat.  The result is centred on its centroid
    with axes of the starting frame.
    """
    b = np.asarray(measured, float)
    count = np.all(np.isfinite(b), axis=2).sum(axis=1)
    if count.max(initial=0) < b.shape[1]:
        raise FitError("no frame shows every cluster marker; cannot define the cluster shape")
    ref = b[int(np.argmax(count))].copy()
    ref -= ref.mean(axis=0)
    for _ in range(n_iter):
        pose = rigid_pose(ref, b)
        local = pose.to_local(b)
        new = np.nanmean(local, axis=0)
        new -= new.mean(axis=0)
        if np.max(np.abs(new - ref)) < 1e-12:
            break
        ref = new
    return ref
