r"""The lab's vertical, direction of progression and floor, read from the marker trials.

Nothing about the lab is assumed: a Vicon lab is usually Z up, an OpenSim or
Motion Analysis one Y up, and the walkway may run along any horizontal axis.

Model.  A standing or walking subject has its feet on the floor and its pelvis
above them.  With :math:`p_t` the centroid of the pelvis markers and
:math:`f_t` the centroid of the foot markers in frame ``t`` (lab coordinates,
m), the mean pelvis-to-feet offset over every frame of every trial

.. math::

    d = \frac{1}{T} \sum_t (p_t - f_t)

points up.  The lab's vertical is the signed lab axis closest to it,

.. math::

    k^* = \arg\max_k |d_k|, \qquad
    \hat u = \operatorname{sign}(d_{k^*})\, e_{k^*}, \qquad
    \theta = \angle(d, \hat u),

and the lab is refused as ambiguous when any one trial's offset is more than
:math:`\theta_{max}` (`MAX_TILT_DEG`) from its nearest lab axis, or when the
trials disagree on that axis.  The floor height is the `FLOOR_PERCENTILE` percentile of
the foot markers' heights :math:`\hat u \cdot x` (marker centres, so it lies a
marker radius above the true floor).

The direction of progression is the horizontal displacement of the pelvis
centroid over each walking trial,

.. math::

    \hat g = \frac{P_h (p_{end} - p_{start})}{\lVert P_h (p_{end} - p_{start}) \rVert},
    \qquad P_h = I - \hat u \hat u^T,

taken from the trial with the longest path (at least `MIN_WALK_M`).  Without a
walking trial it is the static trial's mean heel-to-toe direction, else the
pelvis's posterior-to-anterior direction (PSIS/sacrum to ASIS), projected
onto the floor.

Markers are found by name first (Plug-in-Gait ``LASI``, ``RPSI``, ``SACR``,
``LHEE``, ``RTOE``, ``LANK``; OpenSim's ``R.ASIS``, ``V.Sacral``, ``R.Heel``,
``R.Toe.Tip``, ``L.Ankle.Lat``; any ``Subject:`` prefix ignored).  When a
trial has no such names, geometry stands in: the body's long axis is the lab
axis along which the markers of a frame spread the most (median over
frames); in a moving trial the feet are the end of it whose group of markers
(the nearest `END_FRACTION` of the extent) spreads at least
`MIN_SPREAD_RATIO` times wider across it (the stride parts the feet; the head
is one cluster); a static pose (often arms out) takes its sign from the other
trials, and with none the lab is refused.  The two end groups then stand for
the pelvis and the feet, and the floor is taken from all marker samples.
`LabFrame.evidence` says which rule gave each answer.

The internal frame.  The rest of the toolkit works in one frame whatever the
lab: X the static pose's facing direction (horizontal), Y to the subject's
left, Z up (`LabFrame.internal_from_lab`, :math:`x_{int} = R\,x_{lab}`, same
origin).  The facing :math:`\hat f` is the static trial's mean
sacrum/PSIS-to-ASIS direction on the floor, else its mean heel-to-toe
direction, else the direction of progression; it is snapped to the nearest
horizontal lab axis when within `SNAP_DEG` of it, so that :math:`R` is a
signed permutation of the lab axes.  Why snap: a lab lays its axes along the
walkway and the subject stands on it facing along it to within a few degrees;
the pelvis's own heading in a static trial is that plus the stance's
rotation (5-10 deg is common) and marker placement error, which are not the
lab's orientation.  A permutation keeps the walkway on an axis (as
Plug-in-Gait's progression frame, the lab axis nearest the progression, does),
is exact in floating point (a Z-up lab facing +X is left bit for bit as it
is) and keeps the trials' coordinates recognisable to the lab.  Beyond
`SNAP_DEG` (a diagonal walkway) the measured facing is used as it is.

.. math::

    R = \begin{pmatrix} \hat f^T \\ (\hat u \times \hat f)^T \\ \hat u^T \end{pmatrix}
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from kinematics.io.markers import MarkerTrial
from lowerlimb.errors import InputError

MAX_TILT_DEG = 20.0
"""Largest angle between the pelvis-to-feet offset and a lab axis (deg); a standing pelvis is within a few degrees."""
FLOOR_PERCENTILE = 1.0
"""Percentile of the foot markers' heights taken as the floor (robust to a few ghost samples)."""
MIN_WALK_M = 0.3
"""Shortest horizontal pelvis path (m) that counts as walking."""
END_FRACTION = 0.15
"""Share of the body's extent that makes up each end group in the geometric fallback."""
MIN_SPREAD_RATIO = 1.3
"""In the geometric fallback, the feet's end must spread this many times wider than the head's."""
SNAP_DEG = 20.0
"""A static facing within this angle (deg) of a horizontal lab axis is taken as that axis (module docstring)."""

_PELVIS = re.compile(r"(asis?|psis?|sacr)")
_FEET = re.compile(r"(hee|toe|(?<!sh)ank)")
_HEEL = re.compile(r"hee")
_TOE = re.compile(r"toe")
_ANTERIOR_PELVIS = re.compile(r"asis?")
_POSTERIOR_PELVIS = re.compile(r"(psis?|sacr)")
_AXES = ("X", "Y", "Z")


def _key(name: str) -> str:
    """Lower-case name without subject prefix or punctuation: 'Sub:R.ASIS' -> 'rasis'."""
    return re.sub(r"[^a-z0-9]", "", name.split(":")[-1].lower())


def _pick(trial: MarkerTrial, pattern: re.Pattern) -> list[int]:
    return [i for i, n in enumerate(trial.names) if pattern.search(_key(n))]


def _centroid(trial: MarkerTrial, idx: list[int]) -> np.ndarray:
    """Per-frame centroid of the markers ``idx`` (NaN in frames where all are missing), shape (F, 3)."""
    pos = trial.positions[:, idx, :]
    with np.errstate(invalid="ignore"), _quiet():
        return np.nanmean(pos, axis=1)


class _quiet:
    """Silence numpy's 'mean of empty slice' warnings (all-missing frames give NaN, which we drop)."""

    def __enter__(self):
        import warnings
        self._w = warnings.catch_warnings()
        self._w.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc):
        return self._w.__exit__(*exc)


def _axis_label(v: np.ndarray) -> tuple[str, float]:
    """Nearest signed lab axis of a unit vector and the angle to it (deg)."""
    k = int(np.argmax(np.abs(v)))
    sign = "+" if v[k] >= 0 else "-"
    ang = float(np.degrees(np.arccos(np.clip(abs(v[k]), -1.0, 1.0))))
    return f"{sign}{_AXES[k]}", ang


@dataclass(frozen=True)
class LabFrame:
    """The lab's orientation as the trials show it.

    Attributes
    ----------
    up : ndarray, shape (3,)
        Unit vector along a signed lab axis, pointing away from the floor.
    forward : ndarray, shape (3,)
        Unit horizontal direction of progression (lab coordinates); not snapped to an axis.
    floor_height : float
        Height of the floor along `up` (m, lab origin at 0): the lowest foot-marker centres.
    rotation_to_opensim : ndarray, shape (3, 3)
        ``x_ground = R @ x_lab`` into OpenSim's ground: X forward, Y up, Z = X x Y (to the right).
    evidence : tuple of str
        Which markers and rules gave each answer, with the measured angles and distances.
    walking : bool
        True when `forward` comes from a pelvis path, False when from the feet or pelvis of a pose
        (standing, treadmill).
    facing : ndarray, shape (3,), or None
        Unit horizontal direction the static pose faces (lab coordinates), snapped to a lab axis
        within `SNAP_DEG` (module docstring); None: `forward` stands for it.
    """

    up: np.ndarray
    forward: np.ndarray
    floor_height: float
    rotation_to_opensim: np.ndarray
    evidence: tuple[str, ...]
    walking: bool = True
    facing: np.ndarray | None = None

    @property
    def up_axis(self) -> str:
        """The up axis as a signed label, e.g. ``'+Y'``."""
        return _axis_label(self.up)[0]

    @property
    def facing_axis(self) -> str:
        """The internal X (static facing) as a signed lab-axis label, e.g. ``'-Z'``, with the angle when off it."""
        label, ang = _axis_label(self.internal_from_lab[0])
        return label if ang < 1e-9 else f"{label} ({ang:.1f} deg off)"

    @property
    def internal_from_lab(self) -> np.ndarray:
        """(3, 3) rotation ``x_internal = R @ x_lab`` (module docstring): X facing, Y left, Z up.

        Exactly the identity for a Z-up lab facing +X; a signed permutation whenever the facing was snapped.
        """
        f = self.forward if self.facing is None else self.facing
        if self.facing is None:
            f = f - (f @ self.up) * self.up
            f = f / np.linalg.norm(f)
        return np.vstack([f, np.cross(self.up, f), self.up])

    def describe(self) -> str:
        """One line for the console, e.g. ``'Y up, walking +X'`` (with the angle when off an axis by > 5 deg)."""
        label, ang = _axis_label(self.forward)
        up = self.up_axis
        up = up[1:] if up[0] == "+" else up
        fwd = label if ang <= 5.0 else f"{label} ({ang:.0f} deg off)"
        verb = "walking" if self.walking else "facing"
        text = f"{up} up, {verb} {fwd}, floor at {self.floor_height:.3f} m"
        if self.facing is not None:
            text += f", static facing {self.facing_axis}"
        return text

    def to_json(self) -> dict:
        """The lab as ``summary.json`` states it (lab coordinates, m)."""
        return {"up": self.up_axis, "facing": self.facing_axis, "walking": _axis_label(self.forward)[0]
                if self.walking else None, "forward": self.forward.tolist(), "floor_height_m": self.floor_height,
                "internal_from_lab": self.internal_from_lab.tolist(),
                "internal_frame": "X the static pose's facing, Y left, Z up; x_internal = internal_from_lab @ x_lab "
                                  "(same origin)", "evidence": list(self.evidence)}


def _geometric_ends(trial: MarkerTrial, pose: bool) -> tuple[np.ndarray, np.ndarray, bool, str]:
    """Per-frame centroids of the top and bottom (feet) ends of the body, no names used.

    The feet are the end that spreads wider across the long axis (the stride parts the feet; the
    head is one cluster).  In a pose (``pose=True``: standing, often with the arms out) that rule
    does not hold, so the ends are returned as found and flagged unsure.
    """
    pos = trial.positions
    with _quiet():
        spread = np.nanmax(pos, axis=1) - np.nanmin(pos, axis=1)        # (F, 3)
        k = int(np.argmax(np.nanmedian(spread, axis=0)))
    h = pos[:, :, k]
    with _quiet():
        lo = np.nanmin(h, axis=1, keepdims=True)
        hi = np.nanmax(h, axis=1, keepdims=True)
    band = END_FRACTION * (hi - lo)
    ends = []
    for mask in (h <= lo + band, h >= hi - band):
        sel = np.where(mask[..., None], pos, np.nan)
        with _quiet():
            c = np.nanmean(sel, axis=1)
            across = np.nanstd(np.delete(sel, k, axis=2), axis=1).sum(axis=1)  # spread across the axis per frame
            ends.append((c, float(np.nanmedian(across))))
    (c_lo, s_lo), (c_hi, s_hi) = ends
    sure = not pose and max(s_lo, s_hi) >= MIN_SPREAD_RATIO * min(s_lo, s_hi)
    feet, top = (c_lo, c_hi) if s_lo > s_hi else (c_hi, c_lo)
    rule = "sign from the other trials" if not sure else "feet at the end spreading wider"
    return top, feet, sure, (f"{trial.source}: no pelvis/foot names; geometry: long axis {_AXES[k]}, ends spreading "
                             f"{max(s_lo, s_hi) * 1000:.0f} and {min(s_lo, s_hi) * 1000:.0f} mm, {rule}")


def _ends(trial: MarkerTrial, pose: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool, str]:
    """(pelvis centroid, feet centroid, floor samples, sign is sure, evidence) of one trial."""
    pel, feet = _pick(trial, _PELVIS), _pick(trial, _FEET)
    if pel and feet:
        names = ", ".join(trial.names[i] for i in pel + feet)
        return (_centroid(trial, pel), _centroid(trial, feet), trial.positions[:, feet, :].reshape(-1, 3), True,
                f"{trial.source}: pelvis and feet by name ({names})")
    top, bottom, sure, why = _geometric_ends(trial, pose)
    return top, bottom, trial.positions.reshape(-1, 3), sure, why


def detect_lab(static: MarkerTrial | None, trials: Sequence[MarkerTrial]) -> LabFrame:
    """Find the lab's vertical, direction of progression and floor from the trials.

    Parameters
    ----------
    static : MarkerTrial or None
        The standing trial, metres in lab coordinates.
    trials : sequence of MarkerTrial
        Walking (or other) trials of the same lab, metres.

    Returns
    -------
    LabFrame

    Raises
    ------
    InputError
        No trial, no frame with both ends of the body, a pelvis-to-feet offset more than
        `MAX_TILT_DEG` from every lab axis (one line naming the trial and the angle), or no
        way to tell the direction of progression.
    """
    allt = ([static] if static is not None else []) + list(trials)
    if not allt:
        raise InputError(None, "no marker trial to read the lab from")
    evidence: list[str] = []
    offsets, foot_samples, pelvis_paths = [], [], []
    found = []
    for n, t in enumerate(allt):
        pel, feet, fs, sure, why = _ends(t, pose=static is not None and n == 0)
        evidence.append(why)
        d = pel - feet
        d = d[np.all(np.isfinite(d), axis=1)]
        if len(d) == 0:
            raise InputError(t.source, "no frame has both pelvis and foot markers")
        found.append((t, pel, d, fs, sure))
    sure_up = [d.mean(axis=0) for _, _, d, _, s in found if s]
    if not sure_up:
        raise InputError(allt[0].source, "cannot tell the feet from the head: no pelvis or foot marker names "
                                         "(ASI/PSI/SACR, HEE/TOE/ANK) and no walking trial whose ends tell them apart")
    ref = np.mean([v / np.linalg.norm(v) for v in sure_up], axis=0)
    for t, pel, d, fs, sure in found:
        mean = d.mean(axis=0)
        if not sure and mean @ ref < 0:
            d, mean = -d, -mean
        # each trial must be upright on its own: a tilted trial is refused by name
        u = mean / np.linalg.norm(mean)
        label, ang = _axis_label(u)
        if ang > MAX_TILT_DEG:
            raise InputError(t.source, f"ambiguous lab: the pelvis-to-feet direction is {ang:.1f} deg from the nearest "
                                       f"lab axis ({label}; at most {MAX_TILT_DEG:.0f} deg allowed)")
        evidence.append(f"{t.source}: pelvis {np.linalg.norm(mean):.3f} m above the feet along {label} "
                        f"({ang:.1f} deg off the axis)")
        offsets.append(d)
        foot_samples.append(fs)
        pelvis_paths.append((t, pel))
    dall = np.concatenate(offsets).mean(axis=0)
    k = int(np.argmax(np.abs(dall)))
    up = np.zeros(3)
    up[k] = np.sign(dall[k])
    labels = {_axis_label(o.mean(axis=0) / np.linalg.norm(o.mean(axis=0)))[0] for o in offsets}
    if len(labels) > 1:
        raise InputError(allt[0].source, f"ambiguous lab: the trials disagree on the vertical ({', '.join(sorted(labels))})")

    heights = np.concatenate([fs @ up for fs in foot_samples])
    floor = float(np.nanpercentile(heights, FLOOR_PERCENTILE))
    evidence.append(f"floor at {floor:.3f} m along {_axis_label(up)[0]} (percentile {FLOOR_PERCENTILE:g} of "
                    f"{np.isfinite(heights).sum()} foot-marker samples, or all markers without names)")

    horiz = np.eye(3) - np.outer(up, up)
    forward, best, walking = None, 0.0, True
    for t, pel in pelvis_paths[(1 if static is not None else 0):]:
        ok = np.all(np.isfinite(pel), axis=1)
        if ok.sum() < 2:
            continue
        p = pel[ok]
        step = horiz @ (p[-1] - p[0])
        n = float(np.linalg.norm(step))
        if n >= MIN_WALK_M and n > best:
            best, forward = n, step / n
            src = t.source
    if forward is not None:
        evidence.append(f"{src}: forward {_axis_label(forward)[0]} ({_axis_label(forward)[1]:.1f} deg off) "
                        f"from the pelvis path, {best:.2f} m")
    else:
        # treadmill or walking in place: the feet point the way the subject faces
        forward, why = _facing(allt, horiz)
        walking = False
        evidence.append(f"no pelvis path of {MIN_WALK_M} m; forward: {why}")
    right = np.cross(forward, up)
    rot = np.vstack([forward, up, right])
    facing = None
    if static is not None:
        facing, why = _static_facing(static, up, forward)
        evidence.append(why)
    return LabFrame(up=up, forward=forward, floor_height=floor, rotation_to_opensim=rot, evidence=tuple(evidence),
                    walking=walking, facing=facing)


def _snap(v: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, str]:
    """`v` (unit, horizontal) as the nearest horizontal signed lab axis when within `SNAP_DEG`, else as it is."""
    label, ang = _axis_label(v)
    if ang <= SNAP_DEG:
        k = int(np.argmax(np.abs(v)))
        e = np.zeros(3)
        e[k] = 1.0 if v[k] > 0 else -1.0
        if abs(e @ up) < 0.5:
            return e, f"snapped to {label} ({ang:.1f} deg off, within {SNAP_DEG:g})"
    return v, f"{ang:.1f} deg from {label}, kept as measured (beyond {SNAP_DEG:g} deg)"


def _static_facing(static: MarkerTrial, up: np.ndarray, forward: np.ndarray) -> tuple[np.ndarray, str]:
    """The direction the static pose faces (module docstring) and how it was found."""
    horiz = np.eye(3) - np.outer(up, up)
    try:
        v, why = _facing([static], horiz, order=((_ANTERIOR_PELVIS, _POSTERIOR_PELVIS, "sacrum-to-ASIS"),
                                                 (_TOE, _HEEL, "heel-to-toe")))
    except InputError:
        v = horiz @ forward
        v = v / np.linalg.norm(v)
        why = f"{static.source}: no ASIS/PSIS or heel/toe markers; static facing taken from the progression"
    f, snap = _snap(v, up)
    return f, f"{why}; internal X (static facing) {snap}"


_FEET_FIRST = ((_TOE, _HEEL, "heel-to-toe"), (_ANTERIOR_PELVIS, _POSTERIOR_PELVIS, "sacrum-to-ASIS"))


def _facing(trials: list[MarkerTrial], horiz: np.ndarray, order=_FEET_FIRST) -> tuple[np.ndarray, str]:
    """Facing direction without a pelvis path: mean heel-to-toe, else PSIS/sacrum-to-ASIS (`order`), on the floor."""
    for (front, back, what) in order:
        for t in trials:
            fi, bi = _pick(t, front), _pick(t, back)
            if not (fi and bi):
                continue
            with _quiet():
                v = horiz @ np.nanmean(_centroid(t, fi) - _centroid(t, bi), axis=0)
            n = float(np.linalg.norm(v)) if np.all(np.isfinite(v)) else 0.0
            if n > 0.05:
                f = v / n
                lab, ang = _axis_label(f)
                return f, (f"{t.source}: {lab} ({ang:.1f} deg off) from the mean {what} direction, "
                           f"{n * 1000:.0f} mm")
    raise InputError(trials[0].source, f"cannot tell the direction of progression: no trial's pelvis moves "
                                       f"{MIN_WALK_M} m and no trial has heel and toe or ASIS and PSIS markers")
