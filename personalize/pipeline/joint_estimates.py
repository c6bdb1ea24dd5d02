"""The values the joint-estimation stage hands on: per joint the MRI, motion and fused estimates (static lab frame)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lowerlimb.estimates import Gaussian

from ..fusion import Fused, FusedAxis

__all__ = ["Direction", "CentreEstimates", "AxisEstimates", "AxisLine", "JointEstimates", "pelvis_tissue_scale"]


@dataclass(frozen=True)
class Direction:
    """An axis direction (3,) (any length, any sense) and its 1-sd angle, deg (isotropic across it)."""

    direction: np.ndarray
    sd_deg: float


@dataclass(frozen=True)
class CentreEstimates:
    """A joint centre from the MRI (registered to the lab), from motion, and their fusion (m, m²)."""

    mri: Gaussian
    motion: Gaussian
    fused: Fused


@dataclass(frozen=True)
class AxisEstimates:
    """A joint axis from the MRI (registered to the lab), from motion, and their fusion on the sphere."""

    mri: Direction
    motion: Direction
    fused: FusedAxis


@dataclass(frozen=True)
class AxisLine:
    """A joint axis taken from one source (subtalar, mtp): a point (m) and a direction."""

    point: np.ndarray
    direction: np.ndarray


@dataclass
class JointEstimates:
    """Per side and joint: the estimates of the static lab frame (X forward, Y left, Z up).

    centres[side][joint] : `CentreEstimates` (hip, knee, ankle)
    axes[side][joint] : `AxisEstimates` (knee, ankle)
    lines[side][joint] : `AxisLine` (subtalar, mtp)
    registrations : segment -> `personalize.registration.Registration` (scanner -> lab)
    pelvis : (origin (3,), axes (3, 3)) Plug-in-Gait pelvis frame of the static markers
    pelvis_bone : the same axes convention (x anterior, y left, z up) from the MRI pelvis's ISB frame as the
        model places the bone (`pipeline.model.pelvis_bone_frame`), or None: the model's pelvis frame
    hip_joint : `Fused` of both hip centres (6-vector r, l; sources "mri", "motion_r", "motion_l")
    skin : marker -> `personalize.skin.SkinThickness` under the pelvic markers
    mri_hip_scale : the MRI hip covariance scale in force
    mri_dropped : segment -> why its MRI source was dropped (registration failed its gate; `joints.gate_segment`)
    notes, sources : what the run says about itself (summary.json)
    """

    centres: dict = field(default_factory=dict)
    axes: dict = field(default_factory=dict)
    lines: dict = field(default_factory=dict)
    registrations: dict = field(default_factory=dict)
    pelvis: tuple | None = None
    pelvis_bone: tuple | None = None
    notes: list = field(default_factory=list)
    sources: dict = field(default_factory=dict)
    hip_joint: Fused | None = None
    skin: dict = field(default_factory=dict)
    mri_hip_scale: float = 1.0
    mri_dropped: dict = field(default_factory=dict)


@dataclass(frozen=True)
class JointContext:
    """What every per-joint estimator reads (static lab frame unless said).

    inputs : `personalize.pipeline.SubjectInputs`
    bones : bone -> `personalize.landmarks.BoneLandmarks` (scanner frame)
    joints : joint name -> `personalize.frames.Joint` (scanner frame; model-error term taken out: the MRI
        covariance scales were calibrated on phantoms)
    static : internal marker name -> `Gaussian` static position (`markers.MarkerView`: landmark names)
    meshes : bone -> surface mesh (scanner frame)
    pig : Plug-in-Gait reconstruction of the static trial, or None without the Plug-in-Gait markers
    dynamic : the non-functional motion trials; functional : the hip calibration trial or None (internal names)
    tissue_measured : the soft tissue under all four pelvic markers was measured in the MRI
    say : progress callable
    view : `personalize.pipeline.markers.MarkerView` (the trials under internal names, segment clusters)
    """

    inputs: object
    bones: dict
    joints: dict
    static: dict
    meshes: dict
    pig: object
    dynamic: list
    functional: object
    tissue_measured: bool
    say: object
    view: object = None

    @property
    def markers_on_joint_axes(self) -> bool:
        """The knee and ankle markers sit on the joint axes (Plug-in-Gait's placement) rather than on the palpated
        prominences (`kinematics.io.marker_sets`, ``placement``); a trial without a marker set is Plug-in-Gait."""
        ms = getattr(self.view, "marker_set", None)
        return ms is None or ms.on_joint_axes

    def tissue_scale(self, est) -> tuple | None:
        """`pelvis_tissue_scale` of `est`."""
        return pelvis_tissue_scale(est)

    def joint_axis(self, joint) -> tuple | None:
        """``(origin, axis)`` of `joint` (`personalize.frames.Joint`) for the registration's on-axis projection, or
        None when the markers are on the prominences."""
        return (joint.origin, joint.axis) if self.markers_on_joint_axes else None


def pelvis_tissue_scale(est) -> tuple | None:
    """(k, sd of ln k) of the soft tissue estimated with `est`'s pelvis registration, or None."""
    reg = getattr(est, "registrations", {}).get("pelvis")
    k = getattr(reg, "tissue_scale", None)
    return None if k is None else (float(k), float(getattr(reg, "tissue_scale_log_sd", 0.0)))
