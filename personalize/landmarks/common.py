"""The landmark detectors' results: `Landmark`, `Axis`, `BoneLandmarks`, `LandmarkSet`, and their flags.

The surface they are detected on is `surface.Surface`; the articular
primitives (Hough votes, sphere and cylinder refinement) are in
`shape_fits`, the long-bone axes in `long_bones`.

Nothing in the detectors depends on the scanner axes: every choice is made from the
bone's own geometry (principal axes, extremities, normals), and every random
choice is made over vertex *indices* with a seeded generator, so a rigid
motion of the input moves every output by the same motion.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lowerlimb.errors import InputError
from lowerlimb.estimates import Gaussian
from lowerlimb.bones import side_of

__all__ = [
    "Landmark", "Axis", "BoneLandmarks", "LandmarkSet",
    "FLAG_TRUNCATED", "FLAG_LOW_CONFIDENCE", "FLAG_SIDE_MISMATCH", "FLAG_NAME_MISMATCH", "FLAG_NOT_CLOSED",
]

FLAG_TRUNCATED = "truncated"
FLAG_LOW_CONFIDENCE = "low_confidence"
FLAG_SIDE_MISMATCH = "side_mismatch"
FLAG_NAME_MISMATCH = "name_mismatch"
FLAG_NOT_CLOSED = "not_closed"


# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class Landmark:
    """A point on or in a bone: position (3,) in metres and its 3x3 covariance (m^2)."""

    position: np.ndarray
    cov: np.ndarray

    def to_json(self) -> dict:
        return {"position": _r(self.position), "cov": _r(self.cov, 12)}

    @classmethod
    def from_json(cls, d: dict) -> "Landmark":
        return cls(np.asarray(d["position"], float).reshape(3), np.asarray(d.get("cov", np.zeros((3, 3))), float).reshape(3, 3))

    @property
    def gaussian(self) -> Gaussian:
        return Gaussian(self.position, self.cov)


@dataclass(frozen=True)
class Axis:
    """A directed line: a point (m), a unit direction and the direction's 1-sd angle (deg)."""

    point: np.ndarray
    direction: np.ndarray
    sd_deg: float

    def to_json(self) -> dict:
        return {"point": _r(self.point), "direction": _r(self.direction, 9), "sd_deg": round(float(self.sd_deg), 6)}

    @classmethod
    def from_json(cls, d: dict) -> "Axis":
        return cls(np.asarray(d["point"], float), np.asarray(d["direction"], float), float(d.get("sd_deg", 0.0)))


@dataclass
class BoneLandmarks:
    """Everything detected on one bone (built by a detector, then read-only).

    ``scalars`` (m) are written as ``{"value": v, "sd": s}`` (``sd`` null when
    no fit provides it), like the phantom's truth.
    ``frames`` maps a frame name to ``{"origin": (3,), "rotation": (3, 3)}``
    (axes as columns: X anterior, Y proximal/superior, Z to the subject's
    right, ISB conventions); ``fits`` maps a primitive name to a JSON-ready
    description of the fitted primitive.
    """

    bone: str
    side: str | None
    landmarks: dict[str, Landmark] = field(default_factory=dict)
    axes: dict[str, Axis] = field(default_factory=dict)
    scalars: dict[str, float] = field(default_factory=dict)
    frames: dict[str, dict] = field(default_factory=dict)
    flags: list[str] = field(default_factory=list)
    fits: dict[str, dict] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    scalar_sd: dict[str, float] = field(default_factory=dict)

    def flag(self, flag: str, note: str | None = None) -> None:
        if flag not in self.flags:
            self.flags.append(flag)
        if note:
            self.notes.append(note)

    def to_json(self) -> dict:
        return {
            "landmarks": {k: v.to_json() for k, v in self.landmarks.items()},
            "axes": {k: v.to_json() for k, v in self.axes.items()},
            "scalars": {k: {"value": round(float(v), 9),
                            "sd": (round(float(self.scalar_sd[k]), 9) if k in self.scalar_sd else None)}
                        for k, v in self.scalars.items()},
            "frames": {k: {"origin": _r(f["origin"]), "rotation": _r(f["rotation"], 9)} for k, f in self.frames.items()},
            "flags": list(self.flags),
            "notes": list(self.notes),
        }

    @classmethod
    def from_json(cls, bone: str, d: dict) -> "BoneLandmarks":
        """One bone of a landmarks.json (fits are in fits.json and are not read)."""
        sc = d.get("scalars", {})
        return cls(bone=bone, side=side_of(bone),
                   landmarks={k: Landmark.from_json(v) for k, v in d.get("landmarks", {}).items()},
                   axes={k: Axis.from_json(v) for k, v in d.get("axes", {}).items()},
                   scalars={k: float(v["value"] if isinstance(v, dict) else v) for k, v in sc.items()},
                   frames={k: {"origin": np.asarray(f["origin"], float), "rotation": np.asarray(f["rotation"], float)}
                           for k, f in d.get("frames", {}).items()},
                   flags=list(d.get("flags", [])), notes=list(d.get("notes", [])),
                   scalar_sd={k: float(v["sd"]) for k, v in sc.items() if isinstance(v, dict) and v.get("sd") is not None})


@dataclass
class LandmarkSet:
    """Landmarks of every detected bone plus the bones that could not be used."""

    bones: dict[str, BoneLandmarks] = field(default_factory=dict)
    missing: list[str] = field(default_factory=list)
    rejected: dict[str, str] = field(default_factory=dict)

    def __getitem__(self, bone: str) -> BoneLandmarks:
        return self.bones[bone]

    def __contains__(self, bone: str) -> bool:
        return bone in self.bones

    def to_json(self) -> dict:
        return {
            "units": "m",
            "frame": "input",
            "bones": {k: v.to_json() for k, v in self.bones.items()},
            "rejected": dict(self.rejected),
        }

    def fits_json(self) -> dict:
        return {"units": "m", "frame": "input", "bones": {k: v.fits for k, v in self.bones.items()}}

    @classmethod
    def from_json(cls, d: dict, source: str = "landmarks.json") -> "LandmarkSet":
        """A landmarks.json document (`to_json`); `InputError` naming `source` when it is not one."""
        if not isinstance(d, dict) or not isinstance(d.get("bones"), dict):
            raise InputError(source, "not a landmarks file (no 'bones')")
        if d.get("units", "m") != "m":
            raise InputError(source, f"landmark units must be 'm', got {d.get('units')!r}")
        try:
            bones = {k: BoneLandmarks.from_json(k, v) for k, v in d["bones"].items()}
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(source, f"malformed landmark entry ({' '.join(str(exc).split())})") from None
        return cls(bones=bones, missing=list(d.get("missing_bones", [])), rejected=dict(d.get("rejected", {})))


def _r(a, nd: int = 9):
    return np.round(np.asarray(a, float), nd).tolist()
