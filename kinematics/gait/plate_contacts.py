"""Which foot stands on each force plate: loaded intervals assigned from the foot markers.

`assign_feet` gives each loaded interval of each plate (`kinematics.io.forceplates`)
to the foot standing on it, from the foot markers (heel, toe, ankle): see its
docstring.  Lab frame, metres, seconds.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kinematics.io.forceplates import ForcePlates

__all__ = ["FOOT_MARKERS", "PlateContact", "assign_feet", "foot_markers"]

# Foot markers tried in order, per side: Plug-in-Gait, then common OpenSim/other names.
FOOT_MARKERS = {
    "heel": ("{s}HEE", "{s}HEEL", "{s}.Heel", "{s}CAL", "{s}HEL"),
    "toe": ("{s}TOE", "{s}.Toe", "{s}.Toe.Tip", "{s}TOE2", "{s}MT2", "{s}D2M", "{s}FM2"),
    "ankle": ("{s}ANK", "{s}.Ankle", "{s}LMAL", "{s}LM", "{s}ANKL"),
}


@dataclass(frozen=True)
class PlateContact:
    """One loaded interval of one plate and the foot found on it.

    Attributes
    ----------
    plate : int
        0-based plate index.
    start, stop : int
        Frame range, stop exclusive (frames of the `ForcePlates`).
    start_time, end_time : float, s
    foot : str or None
        ``"R"`` or ``"L"``; None when no single foot can be vouched for.
    cop_distance : dict side -> float, m
        Median distance from the CoP to each foot's heel-toe line (in the plate plane).
    flags : tuple of str
        ``"two feet"``, ``"no foot"``, ``"cop outside plate"``, ``"partial"``
        (interval touches the trial start or end), ``"foot markers missing"``.
    """

    plate: int
    start: int
    stop: int
    start_time: float
    end_time: float
    foot: str | None
    cop_distance: dict = field(default_factory=dict)
    flags: tuple = ()

    @property
    def usable(self) -> bool:
        """One foot, fully on the plate, CoP inside: safe to apply to that foot."""
        return self.foot is not None and not ({"two feet", "cop outside plate", "no foot"} & set(self.flags))

    def describe(self) -> str:
        who = f"{self.foot} foot" if self.foot else "no foot assigned"
        d = ", ".join(f"{s} {v * 100:.1f} cm" for s, v in sorted(self.cop_distance.items()) if np.isfinite(v))
        fl = f" [{'; '.join(self.flags)}]" if self.flags else ""
        return (f"plate {self.plate + 1}: {self.start_time:.3f}-{self.end_time:.3f} s -> {who}"
                f" (CoP to foot line: {d or 'n/a'}){fl}")


def foot_markers(markers, side: str) -> dict:
    """Role (heel, toe, ankle) -> the first `FOOT_MARKERS` name of `side` (``"R"``/``"L"``) present in the trial."""
    out = {}
    for role, cands in FOOT_MARKERS.items():
        for c in cands:
            name = c.format(s=side)
            if name in markers.names:
                out[role] = name
                break
    return out


def _resample(markers, times: np.ndarray) -> np.ndarray:
    """Marker positions (F, M, 3) at `times` (linear interpolation; NaN outside the markers' span)."""
    pos = markers.positions
    if pos.shape[0] == times.shape[0] and np.allclose(markers.time, times, atol=1e-6):
        return pos
    out = np.full((times.shape[0],) + pos.shape[1:], np.nan)
    for j in range(pos.shape[1]):
        for d in range(3):
            v = pos[:, j, d]
            ok = np.isfinite(v)
            if ok.sum() >= 2:
                out[:, j, d] = np.interp(times, markers.time[ok], v[ok], left=np.nan, right=np.nan)
    return out


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + s[:, None] * ab), axis=1)


def assign_feet(plates: ForcePlates, markers, *, max_cop_distance: float = 0.08, max_height: float = 0.15,
                max_speed: float = 1.0, min_frames: int = 3, sides=("R", "L")) -> list[PlateContact]:
    """Assign each loaded interval of each plate to the foot on it.

    For a foot with heel marker h and toe marker t (``FOOT_MARKERS``; the
    ankle marker is used when the toe is missing), projected on the plate
    plane, the CoP p is "under" the foot in a frame when

        d(p, [h, t]) <= max_cop_distance      (distance to the heel-toe segment, m).

    A foot is "on" plate P in a frame when its heel or toe projects inside
    P (1 cm margin), is less than `max_height` above P's surface and moves
    slower than `max_speed` (a swinging foot over the plate is fast).

    The interval goes to the side with the smallest median CoP distance if
    that median is within `max_cop_distance`.  Flags: ``"two feet"`` when
    both feet are on the plate together for at least `min_frames` frames (the
    plate's load cannot be split: ``foot`` is None); ``"no foot"`` when no foot
    is near the CoP; ``"cop outside plate"``; ``"partial"`` when the interval
    touches the first or last frame (a stance cut by the trial);
    ``"foot markers missing"``.

    Parameters
    ----------
    plates : ForcePlates
    markers : MarkerTrial
        Lab-frame marker trajectories (m), same lab as the plates; resampled
        to the plates' time base by linear interpolation when rates differ.

    Returns
    -------
    list of PlateContact, ordered by start time.
    """
    times = plates.time
    pos = _resample(markers, times)
    dt = 1.0 / plates.rate
    feet = {}
    for s in sides:
        names = foot_markers(markers, s)
        if "heel" not in names or not ("toe" in names or "ankle" in names):
            continue
        h = pos[:, markers.index(names["heel"])]
        t = pos[:, markers.index(names.get("toe", names.get("ankle")))]
        feet[s] = (h, t)
    out: list[PlateContact] = []
    n = plates.n_frames
    min_run = max(1, round(0.02 * plates.rate))  # a load shorter than 20 ms is not a foot contact
    for plate in plates:
        for a, b in plate.intervals(min_frames=min_run):
            flags: list[str] = []
            if a == 0 or b == n:
                flags.append("partial")
            if plate.cop_outside[a:b].any():
                flags.append("cop outside plate")
            if not feet:
                flags.append("foot markers missing")
                out.append(PlateContact(plate.index, a, b, float(times[a]), float(times[b - 1]), None, {}, tuple(flags)))
                continue
            cop = plate.cop[a:b]
            nrm = plate.normal
            dist, on = {}, {}
            for s, (h, t) in feet.items():
                hp = h[a:b] - np.outer((h[a:b] - plate.centre) @ nrm, nrm)
                tp = t[a:b] - np.outer((t[a:b] - plate.centre) @ nrm, nrm)
                d = _segment_distance(cop, hp, tp)
                dist[s] = float(np.nanmedian(d)) if np.isfinite(d).any() else np.nan
                frames = np.zeros(b - a, bool)
                for m in (h, t):
                    seg = m[a:b]
                    vel = np.gradient(m, dt, axis=0)[a:b] if m.shape[0] > 1 else np.zeros_like(seg)
                    with np.errstate(invalid="ignore"):
                        frames |= (plate.contains(seg, 0.01) & (plate.height_above(seg) < max_height)
                                   & (np.linalg.norm(vel, axis=1) < max_speed))
                on[s] = frames
            if len(on) >= 2:
                both = np.logical_and.reduce(list(on.values()))
                if both.sum() >= min_frames:
                    flags.append("two feet")
            valid = {s: v for s, v in dist.items() if np.isfinite(v)}
            best = min(valid, key=valid.get) if valid else None
            foot = best if best is not None and valid[best] <= max_cop_distance else None
            if foot is None:
                flags.append("foot markers missing" if not valid else "no foot")
            if "two feet" in flags:
                foot = None
            out.append(PlateContact(plate.index, a, b, float(times[a]), float(times[b - 1]), foot, dist, tuple(flags)))
    out.sort(key=lambda c: (c.start, c.plate))
    return out
