"""Per-frame Gaussian blending of two kinematic chains of the leg.

The hip-first chain (Plug-in-Gait) propagates the pelvis' and thigh's soft-
tissue artefact down the leg; the foot-first chain (Tändl et al. 2010,
`kinematics.gait.foot_to_hip`) starts from the foot and shank, whose markers sit
on thin tissue.  Neither is better in every frame, so each segment's pose is
blended frame by frame with Gaussian weights from how well each chain's
segment frame carries that segment's own markers (issue P1, item 2).

Residual of chain c for segment s in frame f::

    r_cs(f) = sqrt( mean_m | o_cs(f) + R_cs(f) p_csm - x_m(f) |² ),
    p_csm   = median over static frames of R_cs(t)ᵀ (x_m(t) - o_cs(t)),

over the markers m rigidly attached to the segment's bone (`SEGMENT_MARKERS`)
that both trials carry, leaving out those the chains build the frame from
(`FRAME_MARKERS`: a frame always fits them) when two others remain: a chain
whose frame follows the bone's markers rigidly has a small residual.  The two poses are then fused as Gaussians with variances
σ_c² = r_cs² + floor² (`blend_poses`): the foot-to-hip chain gets the weight
w = σ_pig² / (σ_pig² + σ_f2h²), rotations are averaged on SO(3) along the
geodesic and origins linearly.  Joint angles are recomputed from the blended
segments (Plug-in-Gait conventions); each joint centre is blended with the
weights of the segment that carries it (hip: femur; knee and ankle: tibia).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from lowerlimb.errors import InputError
from kinematics.io.markers import MarkerTrial
from kinematics.gait.pig import SegmentPose

__all__ = ["BlendedPoses", "blend_poses", "SEGMENT_MARKERS", "segment_markers", "chain_residuals", "CENTRE_SEGMENT"]

#: markers rigidly attached to each segment's bone (without side letter); pelvis names are complete
SEGMENT_MARKERS = {
    "pelvis": ("RASI", "LASI", "RPSI", "LPSI", "SACR"),
    "femur": ("THI", "THIP", "THIA", "KNE", "KNEM"),
    "tibia": ("TIB", "TIBM1", "TIBM2", "TIBM3", "ANK", "ANKM"),
    "foot": ("HEE", "TOE", "D1M", "D5M"),
}
#: joint centre -> segment whose weights blend it
CENTRE_SEGMENT = {"hip": "femur", "knee": "tibia", "ankle": "tibia"}


#: markers either chain builds the segment's frame from (a frame always fits those): left out of the residual
#: when at least two other markers of the segment remain
FRAME_MARKERS = {"femur": ("THI", "KNE"), "tibia": ("TIB", "ANK"), "foot": ("HEE", "TOE")}


def segment_markers(segment: str, names) -> list[str]:
    """Markers of `names` that judge `segment`'s frame (``pelvis``, ``femur_r``, ``tibia_torsioned_l``, ``foot_r``...).

    The segment's bone markers (`SEGMENT_MARKERS`) other than those the chains build its frame from
    (`FRAME_MARKERS`), or all of them when fewer than two others are present (plain Plug-in-Gait sets).
    """
    names = set(names)
    if segment == "pelvis":
        return [m for m in SEGMENT_MARKERS["pelvis"] if m in names]
    kind, side = segment.rsplit("_", 1)
    kind = "tibia" if kind.startswith("tibia") else kind
    S = side.upper()
    marks = [S + m for m in SEGMENT_MARKERS.get(kind, ()) if S + m in names]
    held_out = [m for m in marks if m[1:] not in FRAME_MARKERS.get(kind, ())]
    return held_out if len(held_out) >= 2 else marks


def chain_residuals(segments: dict, trial: MarkerTrial, static_segments: dict, static: MarkerTrial) -> dict:
    """Per-frame rigid residual (m) of each segment frame of one chain (module docstring).

    Parameters
    ----------
    segments, static_segments : dict name -> SegmentPose of the chain on `trial` and on `static`
    trial, static : MarkerTrial

    Returns
    -------
    dict segment -> (F,) m; NaN in frames where fewer than two of its markers are visible,
    and for segments with fewer than two markers in both trials.
    """
    out = {}
    for name, pose in segments.items():
        ref = static_segments.get(name)
        marks = [m for m in segment_markers(name, trial.names) if m in static.names]
        F = len(pose.origin)
        if ref is None or len(marks) < 2:
            out[name] = np.full(F, np.nan)
            continue
        local = np.stack([np.nanmedian(ref.to_local(static.marker(m)), axis=0) for m in marks])   # (M, 3)
        x = np.stack([trial.marker(m) for m in marks], axis=1)                                    # (F, M, 3)
        pred = pose.origin[:, None, :] + np.einsum("fij,mj->fmi", pose.axes, local)
        d2 = np.sum((pred - x) ** 2, axis=2)
        n = np.sum(np.isfinite(d2), axis=1)
        with np.errstate(invalid="ignore"):
            r = np.sqrt(np.nansum(d2, axis=1) / np.maximum(n, 1))
        out[name] = np.where(n >= 2, r, np.nan)
    return out


@dataclass(frozen=True)
class BlendedPoses:
    """Per-frame blend of two pose sequences.

    R : (F, 3, 3) rotations (segment -> lab); t : (F, 3) m origins
    weight_a, weight_b : (F,) weight each chain received (sum 1; NaN where both missing)
    sd : (F,) m, fused pose error scale √(σ_a² σ_b² / (σ_a² + σ_b²))
    """

    R: np.ndarray
    t: np.ndarray
    weight_a: np.ndarray
    weight_b: np.ndarray
    sd: np.ndarray

    def as_segment_pose(self) -> SegmentPose:
        """The blend as a `kinematics.gait.pig.SegmentPose` (origin, axes)."""
        return SegmentPose(self.t, self.R)


def _unpack_pose(p, name: str):
    if isinstance(p, tuple) and len(p) >= 2:
        R, t = p[0], p[1]
    elif hasattr(p, "axes") and hasattr(p, "origin"):
        R, t = p.axes, p.origin
    elif hasattr(p, "R") and hasattr(p, "t"):
        R, t = p.R, p.t
    else:
        raise InputError(name, "poses must be (R, t), a SegmentPose or a RigidPose")
    R, t = np.asarray(R, float), np.asarray(t, float)
    if R.ndim == 2:
        R, t = R[None], t.reshape(1, 3)
    if R.shape[1:] != (3, 3) or t.shape != (R.shape[0], 3):
        raise InputError(name, f"poses must be R (F, 3, 3) and t (F, 3), got {R.shape} and {t.shape}")
    return R, t


def blend_poses(poses_a, poses_b, residuals_a, residuals_b, *, floor: float = 1e-4) -> BlendedPoses:
    """Blend two chains' segment poses per frame with Gaussian weights from their residuals.

    Model: each chain's pose error is Gaussian with variance proportional to
    its squared marker residual, σ² = r² + floor².  The product of the two
    Gaussians weights chain b by w_b = σ_a² / (σ_a² + σ_b²) and

        R = R_a exp(w_b log(R_aᵀ R_b)),    t = (1 - w_b) t_a + w_b t_b,

    the rotation being the weighted geodesic (Karcher) mean on SO(3) of the
    two rotations.  A frame missing in one chain (NaN) takes the other.

    Parameters
    ----------
    poses_a, poses_b : (R (F, 3, 3), t (F, 3)), SegmentPose or RigidPose
    residuals_a, residuals_b : scalar or (F,) m, rms marker residual of each chain
        (NaN: chain unusable in that frame)
    floor : m, residual floor that keeps a perfect fit from taking all the weight

    Returns
    -------
    BlendedPoses
    """
    Ra, ta = _unpack_pose(poses_a, "poses_a")
    Rb, tb = _unpack_pose(poses_b, "poses_b")
    F = len(Ra)
    if len(Rb) != F:
        raise InputError("blend_poses", f"chains have {F} and {len(Rb)} frames")
    ra = np.broadcast_to(np.asarray(residuals_a, float), (F,))
    rb = np.broadcast_to(np.asarray(residuals_b, float), (F,))
    if np.any(ra < 0) or np.any(rb < 0):
        raise InputError("blend_poses", "residuals must be non-negative")
    va, vb = ra**2 + floor**2, rb**2 + floor**2
    ok_a = np.all(np.isfinite(Ra), axis=(1, 2)) & np.all(np.isfinite(ta), axis=1) & np.isfinite(va)
    ok_b = np.all(np.isfinite(Rb), axis=(1, 2)) & np.all(np.isfinite(tb), axis=1) & np.isfinite(vb)
    with np.errstate(invalid="ignore", divide="ignore"):
        wb = np.where(ok_a & ok_b, va / (va + vb), np.where(ok_b, 1.0, np.where(ok_a, 0.0, np.nan)))
        sd = np.where(ok_a & ok_b, np.sqrt(va * vb / (va + vb)), np.where(ok_b, np.sqrt(vb), np.where(ok_a, np.sqrt(va), np.nan)))
    both = ok_a & ok_b
    R = np.full((F, 3, 3), np.nan)
    t = np.full((F, 3), np.nan)
    R[ok_a & ~ok_b], t[ok_a & ~ok_b] = Ra[ok_a & ~ok_b], ta[ok_a & ~ok_b]
    R[ok_b & ~ok_a], t[ok_b & ~ok_a] = Rb[ok_b & ~ok_a], tb[ok_b & ~ok_a]
    if both.any():
        qa = Rotation.from_matrix(Ra[both])
        qb = Rotation.from_matrix(Rb[both])
        rel = (qa.inv() * qb).as_rotvec()
        R[both] = (qa * Rotation.from_rotvec(wb[both, None] * rel)).as_matrix()
        t[both] = (1 - wb[both, None]) * ta[both] + wb[both, None] * tb[both]
    return BlendedPoses(R, t, 1.0 - wb, wb, sd)
