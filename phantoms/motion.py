"""Motion phantoms: the phantom skeleton driven through trials, seen through skin markers.

Trials (coordinates of `phantoms.skeleton`, then markers):

* ``static``: quiet standing in the constructed pose (2 s);
* ``gait_NN``: walking at 1.25 m/s with normative joint-angle curves (hip
  flexion about -6..37 deg, knee flexion 4..59 deg, ankle -16..10 deg,
  small knee ab/adduction and rotation), left leg half a cycle behind;
* ``crouch_AAA_NN``: squats to 100 deg knee flexion with the feet turned out
  so that the angle between them is AAA degrees (0, 30, 60, 90, 120, 180;
  Pronost et al. 2010), the pelvis lowered to keep the heels at their height;
  the knee rotates internally 15-25 deg and goes 2-5 deg into varus with
  flexion at every foot angle, the turnout is taken by the hips (70 %) and
  the knees (30 %) (`crouch_coordinates`, sources there);
* ``functional_hip`` (45 deg) and ``functional_hip_RR``: star-arc hip
  calibration (Camomilla et al. 2006): 8 excursions of RR degrees in the
  flexion-abduction plane then a circumduction, right hip then left hip.

The knee translations follow the skeleton's knee laws exactly.

Markers: the skeleton's STA-free sites plus

* soft-tissue artefact (STA), a linear function of the joint angles (relative
  to standing) per segment: a rigid displacement of the segment's skin
  (translation mostly proximal-distal, rotation mostly about the
  medio-lateral and the long axis) plus a marker-specific deformation::

      d_m(t) = sum_k phi_k(t) (g_k + w_k x (p_m - c) + e_mk)

  (body frame; phi_k the driving angles: pelvis <- hip flexions, thigh <-
  hip angles and knee flexion, shank <- knee flexion/rotation and ankle,
  foot <- ankle and subtalar).  Amplitudes over the reference excursion
  (hip flexion 35 deg, ab/adduction 9 deg, rotation 17 deg; knee flexion 60 deg,
  rotation 14 deg; ankle 20 deg): thigh 10-20 mm, shank 5-15 mm,
  pelvis about 5 mm, foot 2-3 mm, drawn per seed; markers over bony
  prominences move less (knee 45-60 %, malleoli 20-30 %, TIBM3 15-20 % of
  their segment's amplitude); the bone-fixed validation markers TIBM1/TIBM2
  have none; the wand markers THI and TIB add a tangential wobble (6-10 mm),
  the wand amplifying the skin's rotation about the segment's long axis;
* white measurement noise (default sd 0.5 mm);
* optional gaps (one short, one long per dynamic trial).

Everything is vectorised over frames (one FK call per trial).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline

from kinematics.io.markers import MarkerTrial

from .skeleton import DEVICE_MARKERS, EXTRA_MARKERS, PIG_MARKERS, SIDES, PhantomSkeleton, phantom_skeleton

__all__ = ["PhantomTrial", "SoftTissueModel", "soft_tissue_model", "gait_coordinates", "crouch_coordinates",
           "functional_hip_coordinates", "static_coordinates", "observe", "make_trials", "write_trials",
           "marker_names", "ANGLE_COLUMNS", "CROUCH_FOOT_ANGLES"]

CROUCH_FOOT_ANGLES = (0, 30, 60, 90, 120, 180)
#: true Plug-in-Gait angle columns of truth/<trial>_angles.mot (degrees)
ANGLE_COLUMNS = tuple(f"{j}_{a}_{s}" for s in SIDES for j in ("hip", "knee", "ankle")
                      for a in ("flexion", "adduction", "rotation"))


def marker_names(extra: bool = True, device: bool = True) -> tuple[str, ...]:
    """Marker labels written to the C3D files (Plug-in-Gait set, optional extras, validation device)."""
    groups = PIG_MARKERS + (EXTRA_MARKERS if extra else ()) + (DEVICE_MARKERS if device else ())
    return tuple(f"{S}{m}" for S in ("R", "L") for m in groups)


# --------------------------------------------------------------------------- soft-tissue artefact
_SEGMENT_DRIVERS = {
    "pelvis": ("hip_flexion_r", "hip_flexion_l"),
    "femur": ("hip_flexion_{s}", "hip_adduction_{s}", "hip_rotation_{s}", "knee_flexion_{s}"),
    "tibia": ("knee_flexion_{s}", "knee_rotation_{s}", "ankle_angle_{s}"),
    "calcn": ("ankle_angle_{s}", "subtalar_angle_{s}"),
}
#: reference excursion of each driving angle (rad): the amplitude ranges of `_AMPLITUDE` are the STA
#: over these excursions.  Hip and knee axial rotation use the excursions of the tasks in which their
#: STA was measured: thigh markers move 1-5 cm over an active hip rotation task (Fiorentino et al. 2017,
#: Gait Posture 55:184, dual fluoroscopy) and shank markers up to about 15 mm in pivoting tasks with
#: 10-15 deg of tibial rotation (Akbarshahi et al. 2010; Kefala et al. 2017), not the few degrees of gait.
_REFERENCE = {"hip_flexion": 0.6, "hip_adduction": 0.15, "hip_rotation": 0.3, "knee_flexion": 1.05,
              "knee_rotation": 0.25, "ankle_angle": 0.35, "subtalar_angle": 0.1}
#: amplitude of a marker relative to its segment's (range drawn per marker)
_MARKER_FACTOR = {"KNE": (0.45, 0.6), "KNEM": (0.45, 0.6), "ANK": (0.2, 0.3), "ANKM": (0.2, 0.3), "TIBM3": (0.15, 0.2)}
#: tangential wobble of the wand markers over the reference excursion, m
_WAND_WOBBLE = {"THI": (6e-3, 10e-3), "TIB": (6e-3, 10e-3)}
_AMPLITUDE = {"pelvis": (4e-3, 6e-3), "femur": (10e-3, 20e-3), "tibia": (5e-3, 15e-3), "calcn": (2e-3, 3e-3)}


@dataclass(frozen=True)
class SoftTissueModel:
    """Linear STA model: displacement (body frame) = coefficients[m] @ (phi - phi_standing).

    markers : tuple of str
    drivers : tuple of tuple of str, per marker the coordinate names driving it
    coefficients : tuple of ndarray (3, k), m/rad, body frame of the marker's body
    amplitude : dict segment key -> target amplitude (m) over the reference excursion
    """

    markers: tuple
    drivers: tuple
    coefficients: tuple
    amplitude: dict

    def displacement(self, sk: PhantomSkeleton, q: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """Lab displacement (F, M, 3) of every marker of `markers` for poses q (F, n_q)."""
        ix = sk.model.coordinate_index
        out = np.zeros((q.shape[0], len(self.markers), 3))
        for j, (m, drv, C) in enumerate(zip(self.markers, self.drivers, self.coefficients)):
            if not drv:
                continue
            cols = [ix(c) for c in drv]
            phi = q[:, cols] - sk.standing_q[cols]
            local = phi @ C.T                                          # (F, 3) body frame
            b = sk.model.body_index(sk.sites[m].body)
            out[:, j] = np.einsum("fij,fj->fi", rotations[:, b], local)
        return out


def soft_tissue_model(sk: PhantomSkeleton, names, seed: int, scale: float = 1.0) -> SoftTissueModel:
    """Draw the STA coefficients of the markers `names` (see module docstring)."""
    rng = np.random.default_rng([int(seed), 11])
    by_seg: dict[tuple, list[str]] = {}
    for n in names:
        body = sk.sites[n].body
        key = body.split("_")[0]
        side = body[-1] if key != "pelvis" else ""
        by_seg.setdefault((key, side), []).append(n)
    coefs, drivers, amps = {}, {}, {}
    for (key, side), ms in by_seg.items():
        drv = tuple(d.format(s=side) for d in _SEGMENT_DRIVERS[key])
        k = len(drv)
        ref = np.array([_REFERENCE[d.rsplit("_", 1)[0] if d[-2] == "_" else d] for d in drv])
        # rigid skin motion: translation mostly proximal-distal (z), rotation about medio-lateral (y) and long (z) axes
        g = rng.normal(size=(3, k)) * np.array([[0.35], [0.25], [1.0]])
        w = rng.normal(size=(3, k)) * np.array([[0.2], [1.0], [1.0]]) * 0.12     # rad per rad
        pts = np.array([sk.sites[m].offset for m in ms])
        c = pts.mean(axis=0)
        C = {}
        for m, p in zip(ms, pts):
            rigid = g * 0.01 + np.cross(w.T, p - c).T                      # (3, k), m/rad
            e = rng.normal(size=(3, k)) * 0.004                              # marker-specific deformation
            C[m] = rigid + e
        amp = rng.uniform(*_AMPLITUDE[key]) * scale
        for m in ms:
            # markers over bony prominences move less than those over muscle (marker-specific amplitude)
            lo, hi = _MARKER_FACTOR.get(m[1:], (0.8, 1.0))
            peak = np.linalg.norm(C[m] * ref)              # quadrature sum over the drivers (never ~0)
            coefs[m] = C[m] * (amp * rng.uniform(lo, hi) / peak if peak > 0 else 0.0)
            drivers[m] = drv
            if m[1:] in _WAND_WOBBLE and key in ("femur", "tibia"):
                # wand markers: the wand's base turns with the skin about the long axis and the
                # wand amplifies it into a tangential displacement
                p = sk.sites[m].offset
                tang = np.cross(np.array([0.0, 0.0, 1.0]), p - p[2] * np.array([0.0, 0.0, 1.0]))
                tang /= np.linalg.norm(tang)
                c = rng.normal(size=k)
                c *= rng.uniform(*_WAND_WOBBLE[m[1:]]) / np.linalg.norm(c * ref)
                coefs[m] = coefs[m] + np.outer(tang, c)
        amps[f"{key}{'_' + side if side else ''}"] = amp
    out_c, out_d = [], []
    for n in names:
        if n[1:] in ("TIBM1", "TIBM2"):        # rigid to the tibia (the seed's bow device)
            out_c.append(np.zeros((3, 0)))
            out_d.append(())
        else:
            out_c.append(coefs[n])
            out_d.append(drivers[n])
    return SoftTissueModel(tuple(names), tuple(out_d), tuple(out_c), amps)


# --------------------------------------------------------------------------- coordinate trajectories
def _periodic(points, phase):
    """Periodic cubic spline through (phase, degrees) key points, evaluated at phase (mod 1), radians."""
    x, y = np.array(points, float).T
    if x[-1] != 1.0:
        x, y = np.append(x, 1.0), np.append(y, y[0])
    y[-1] = y[0]
    return np.radians(CubicSpline(x, y, bc_type="periodic")(np.mod(phase, 1.0)))


_GAIT = {
    "hip_flexion": [(0, 33), (0.1, 30), (0.3, 12), (0.5, -6), (0.6, 0), (0.75, 25), (0.87, 37)],
    "hip_adduction": [(0, 2), (0.15, 6), (0.45, -1), (0.65, -6), (0.85, -1)],
    "hip_rotation": [(0, 3), (0.3, -2), (0.6, -6), (0.8, 4)],
    "knee_flexion": [(0, 5), (0.13, 18), (0.38, 4), (0.6, 38), (0.72, 59), (0.86, 30), (0.95, 6)],
    "knee_adduction": [(0, 0.5), (0.15, 1.5), (0.45, 0), (0.7, -2.5), (0.9, 0)],
    "knee_rotation": [(0, -2), (0.15, 2), (0.4, -3), (0.72, 6), (0.95, -2)],
    "ankle_angle": [(0, 0), (0.08, -6), (0.45, 10), (0.62, -16), (0.75, -2), (0.9, 1)],
    "subtalar_angle": [(0, -2), (0.1, -4), (0.4, 2), (0.62, 5), (0.8, 0)],
}


def _set(q, sk, name, values):
    q[:, sk.model.coordinate_index(name)] = values


def static_coordinates(sk: PhantomSkeleton, rate: float, duration: float = 2.0) -> np.ndarray:
    """Quiet standing: the constructed pose in every frame, shape (F, n_q)."""
    n = max(int(round(duration * rate)), 2)
    return sk.complete(np.repeat(sk.standing_q[None], n, axis=0))


def gait_coordinates(sk: PhantomSkeleton, rate: float, cycles: float = 2.0, speed: float = 1.25,
                     cycle_time: float = 1.1, rng: np.random.Generator | None = None) -> np.ndarray:
    """Walking: normative curves (phase 0 = right heel strike), left half a cycle later; (F, n_q)."""
    rng = rng or np.random.default_rng(0)
    F = max(int(round(cycles * cycle_time * rate)), 2)
    t = np.arange(F) / rate
    ph0 = rng.uniform(0, 1)
    q = np.repeat(sk.standing_q[None], F, axis=0)
    for s, shift in (("r", 0.0), ("l", 0.5)):
        phase = t / cycle_time + ph0 + shift
        for name, pts in _GAIT.items():
            gain = rng.uniform(0.92, 1.08)
            _set(q, sk, f"{name}_{s}", gain * _periodic(pts, phase))
    phase = t / cycle_time + ph0
    ix = sk.model.coordinate_index
    q0 = sk.standing_q
    _set(q, sk, "pelvis_tilt", q0[ix("pelvis_tilt")] + np.radians(1.5) * np.sin(4 * np.pi * phase))
    _set(q, sk, "pelvis_list", np.radians(4.0) * np.sin(2 * np.pi * phase))
    _set(q, sk, "pelvis_rotation", np.radians(5.0) * np.sin(2 * np.pi * phase + np.pi / 2))
    _set(q, sk, "pelvis_tx", q0[ix("pelvis_tx")] + speed * t)
    _set(q, sk, "pelvis_ty", q0[ix("pelvis_ty")] + 0.02 * np.sin(2 * np.pi * phase))
    _set(q, sk, "pelvis_tz", q0[ix("pelvis_tz")] + 0.015 * np.cos(4 * np.pi * phase) - 0.02)
    return sk.complete(q)


def _heel_compensation(sk: PhantomSkeleton, q: np.ndarray) -> np.ndarray:
    """Lower the pelvis so the mean heel height stays at its standing value."""
    st = sk.state(q)
    h = sk.sites_lab(st, ["RHEE", "LHEE"])[..., 2].mean(axis=1)
    h0 = sk.sites_lab(sk.state(sk.standing_q), ["RHEE", "LHEE"])[0, :, 2].mean()
    q = q.copy()
    q[:, sk.model.coordinate_index("pelvis_tz")] -= h - h0
    return q


def crouch_coordinates(sk: PhantomSkeleton, foot_angle_deg: float, rate: float, duration: float = 3.0,
                       depth: float = 1.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """One crouch (down and up) with the feet turned out by ``foot_angle_deg / 2`` each; (F, n_q).

    Knee flexion reaches 100 deg (x U(0.95, 1.05) per side), hip flexion 85 deg,
    ankle dorsiflexion 28 deg, the pelvis tilts 18 deg forward and is lowered
    to keep the heels at their height (`_heel_compensation`).

    The knee's secondary rotations are those of real knees in weight-bearing
    squats, the same at every foot angle (they are a property of the joint):

    * tibial internal rotation coupled to flexion, ``IR_max g(a1)`` with
      ``IR_max ~ U(15, 25) deg`` per side at 100 deg flexion and
      ``g = (1 - exp(-a1/0.5 rad)) / (1 - exp(-1.75/0.5))`` rising fastest in the first 30 deg
      (the screw-home) then levelling: Qi et al. 2013 (J Biomech 46:1576,
      dual fluoroscopy, lunge: internal rotation rises sharply from 0 to 30 deg,
      varies little from 30 to 120 deg); Moro-oka et al. 2008 (J Orthop Res 26:428,
      squat: about 20 deg over 0-120 deg); wide-based squats show the same
      rotation with flexion (JSSM 2012, 11:695);
    * varus (knee adduction) rising by ``U(2, 5) deg`` at full flexion (a few
      degrees: Qi et al. 2013; Kefala et al. 2017 rarely more than 6 deg).

    The foot angle (turnout) is taken 70 % by hip external rotation and 30 %
    by knee (tibiofemoral) external rotation, constant through the trial
    (Hardaker, Erickson & Myers 1984: a 180 deg turnout is 60-70 % hip rotation
    and 30-40 % knee, tibia and foot; the phantom has no midfoot joint, so the
    knee carries the whole non-hip share and the angle between the feet is the
    nominal one).  Wide stances add hip abduction (up to 20 deg at 180 deg).
    """
    rng = rng or np.random.default_rng(0)
    F = max(int(round(duration * rate)), 2)
    t = np.arange(F) / rate
    s_ = depth * 0.5 * (1 - np.cos(2 * np.pi * t / duration))        # 0 -> 1 -> 0
    half = np.radians(foot_angle_deg) / 2
    wide = foot_angle_deg / 180.0
    q = np.repeat(sk.standing_q[None], F, axis=0)
    ix = sk.model.coordinate_index
    q0 = sk.standing_q
    for s in SIDES:
        g = rng.uniform(0.95, 1.05)
        flex = g * np.radians(100) * s_
        ir_max, varus = np.radians(rng.uniform(15.0, 25.0)), np.radians(rng.uniform(2.0, 5.0))
        screw = (1 - np.exp(-flex / 0.5)) / (1 - np.exp(-np.radians(100) / 0.5))
        _set(q, sk, f"knee_flexion_{s}", q0[ix(f"knee_flexion_{s}")] + flex)
        _set(q, sk, f"hip_flexion_{s}", q0[ix(f"hip_flexion_{s}")] + g * np.radians(85) * s_)
        _set(q, sk, f"hip_rotation_{s}", q0[ix(f"hip_rotation_{s}")] - 0.7 * half - np.radians(3) * s_)
        _set(q, sk, f"hip_adduction_{s}", q0[ix(f"hip_adduction_{s}")] - np.radians(20) * wide * s_ - np.radians(2) * wide)
        _set(q, sk, f"knee_rotation_{s}", q0[ix(f"knee_rotation_{s}")] - 0.3 * half + ir_max * screw)
        _set(q, sk, f"knee_adduction_{s}", q0[ix(f"knee_adduction_{s}")] + varus * s_)
        _set(q, sk, f"ankle_angle_{s}", g * np.radians(28) * s_)
        _set(q, sk, f"subtalar_angle_{s}", -np.radians(4) * wide * s_)
    _set(q, sk, "pelvis_tilt", q0[ix("pelvis_tilt")] + np.radians(18) * s_)
    return _heel_compensation(sk, sk.complete(q))


def star_arc(R: float, n_out: int, n_circ: int, ramp_fraction: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Hip flexion and abduction (rad) of a star-arc calibration (Camomilla et al. 2006).

    Eight out-and-back excursions of amplitude `R` (rad) every 45 deg, `n_out` samples each,
    then a circumduction of `n_circ` samples, faded in and out over `ramp_fraction` of it.
    Returns two arrays of 8 n_out + n_circ samples.
    """
    flex, abd = [], []
    for psi in np.radians(np.arange(0, 360, 45)):
        s_ = 0.5 * (1 - np.cos(2 * np.pi * np.arange(n_out) / n_out))
        flex.append(R * np.cos(psi) * s_)
        abd.append(R * np.sin(psi) * s_)
    a = 2 * np.pi * np.arange(n_circ) / n_circ
    k = np.arange(n_circ)
    ramp = (np.clip(k / (ramp_fraction * n_circ), 0, 1) * np.clip((n_circ - k) / (ramp_fraction * n_circ), 0, 1)
            if ramp_fraction > 0 else 1.0)
    flex.append(R * np.sin(a) * ramp)
    abd.append(R * (1 - np.cos(a)) / 2 * ramp)
    return np.concatenate(flex), np.concatenate(abd)


def functional_hip_coordinates(sk: PhantomSkeleton, range_deg: float, rate: float, time_scale: float = 1.0,
                               rng: np.random.Generator | None = None) -> np.ndarray:
    """Star-arc hip calibration: right then left hip, 8 star excursions of `range_deg` then a circumduction."""
    rng = rng or np.random.default_rng(0)
    R = np.radians(range_deg)
    T_out, T_circ = 1.0 * time_scale, 2.0 * time_scale
    n_out, n_circ = max(int(round(T_out * rate)), 4), max(int(round(T_circ * rate)), 8)
    flex, abd = star_arc(R, n_out, n_circ, ramp_fraction=0.15)
    n1 = flex.size
    F = 2 * n1
    q = np.repeat(sk.standing_q[None], F, axis=0)
    ix = sk.model.coordinate_index
    q0 = sk.standing_q
    t = np.arange(F) / rate
    for k, s in enumerate(SIDES):
        sl = slice(k * n1, (k + 1) * n1)
        q[sl, ix(f"hip_flexion_{s}")] += flex
        q[sl, ix(f"hip_adduction_{s}")] -= abd                          # abduction is negative adduction
        q[sl, ix(f"hip_rotation_{s}")] += np.radians(5) * np.sin(2 * np.pi * np.arange(n1) / n1 * 3)
        q[sl, ix(f"knee_flexion_{s}")] += np.radians(10) * (np.abs(flex) / max(R, 1e-9))
    _set(q, sk, "pelvis_list", q0[ix("pelvis_list")] + np.radians(1.0) * np.sin(2 * np.pi * t / 3.1))
    _set(q, sk, "pelvis_tilt", q0[ix("pelvis_tilt")] + np.radians(1.0) * np.sin(2 * np.pi * t / 2.3))
    _set(q, sk, "pelvis_ty", q0[ix("pelvis_ty")] + 0.003 * np.sin(2 * np.pi * t / 4.3))
    return sk.complete(q)


# --------------------------------------------------------------------------- markers
@dataclass(frozen=True)
class PhantomTrial:
    """One motion-phantom trial.

    name : file stem (``gait_01``); kind : static, gait, crouch or functional
    q : (F, n_q) true coordinates (rad, m); time : (F,) s
    markers : MarkerTrial as written to the C3D (lab, metres, STA + noise + gaps)
    clean : (F, M, 3) m, STA-free noise-free marker centres
    sta : (F, M, 3) m, soft-tissue displacement
    meta : dict (foot_angle_deg, range_deg, ...)
    """

    name: str
    kind: str
    q: np.ndarray
    time: np.ndarray
    markers: MarkerTrial
    clean: np.ndarray
    sta: np.ndarray
    meta: dict = field(default_factory=dict)


def observe(sk: PhantomSkeleton, q: np.ndarray, rate: float, names, *, sta: SoftTissueModel | None = None,
            noise_sd: float = 0.0005, gaps: bool = False, rng: np.random.Generator | None = None,
            name: str = "trial", kind: str = "gait", meta: dict | None = None) -> PhantomTrial:
    """Markers of poses q (F, n_q): STA-free sites + soft-tissue artefact + noise (+ gaps)."""
    rng = rng or np.random.default_rng(0)
    names = tuple(names)
    st = sk.state(q)
    clean = sk.sites_lab(st, names)
    disp = sta.displacement(sk, q, st.rotations) if sta is not None else np.zeros_like(clean)
    pos = clean + disp + (rng.normal(scale=noise_sd, size=clean.shape) if noise_sd > 0 else 0.0)
    F = q.shape[0]
    if gaps and F > 60:
        # one short gap (5 frames: filled by the readers) and one long gap (0.3 s: reported, never invented)
        j_short, j_long = rng.choice([i for i, n in enumerate(names) if n[1:] in ("THI", "TIB", "KNE", "HEE")], 2, replace=False)
        a = int(rng.integers(10, F - 40))
        pos[a:a + 5, j_short] = np.nan
        n_long = min(int(round(0.3 * rate)), F // 3)
        b = int(rng.integers(10, F - n_long - 10))
        pos[b:b + n_long, j_long] = np.nan
    time = np.arange(F) / rate
    trial = MarkerTrial(names, pos, float(rate), time, f"{name}.c3d", {"subject": f"phantom{sk.seed}"})
    return PhantomTrial(name, kind, q, time, trial, clean, disp, dict(meta or {}))


def make_trials(ph, seed: int = 0, *, rate: float = 100.0, gait_trials: int = 2, gait_cycles: float = 2.0,
                crouch_angles=CROUCH_FOOT_ANGLES, crouch_repeats: int = 1, crouch_duration: float = 3.0,
                functional_ranges=(20, 30, 45), functional_time_scale: float = 1.0, static_duration: float = 2.0,
                sta: bool = True, sta_scale: float = 1.0, noise_sd: float = 0.0005, gaps: bool = False,
                extra_markers: bool = True, device_markers: bool = True, skeleton: PhantomSkeleton | None = None):
    """Build every trial of a motion phantom (no file written).

    Returns
    -------
    (PhantomSkeleton, list of PhantomTrial, SoftTissueModel or None)
    """
    from lowerlimb.errors import InputError

    if not (1.0 <= rate <= 2000.0):
        raise InputError("rate", f"{rate} Hz is outside 1-2000 Hz")
    if noise_sd < 0 or noise_sd > 0.01:
        raise InputError("noise_sd", f"{noise_sd} m is outside 0-0.01 m (give metres)")
    for a in crouch_angles:
        if not (0 <= a <= 180):
            raise InputError("crouch_angles", f"foot angle {a} is outside 0-180 degrees")
    for r in functional_ranges:
        if not (5 <= r <= 60):
            raise InputError("functional_ranges", f"range {r} is outside 5-60 degrees")
    sk = skeleton or phantom_skeleton(ph, seed)
    names = marker_names(extra_markers, device_markers)
    stm = soft_tissue_model(sk, names, seed, sta_scale) if sta else None
    rng = np.random.default_rng([int(seed), 23])
    trials = []

    def add(name, kind, q, meta=None, allow_gaps=True):
        trials.append(observe(sk, q, rate, names, sta=stm, noise_sd=noise_sd, gaps=gaps and allow_gaps,
                              rng=np.random.default_rng([int(seed), 29, len(trials)]), name=name, kind=kind, meta=meta))

    add("static", "static", static_coordinates(sk, rate, static_duration), allow_gaps=False)
    for i in range(gait_trials):
        add(f"gait_{i + 1:02d}", "gait", gait_coordinates(sk, rate, gait_cycles, rng=rng))
    for a in crouch_angles:
        for i in range(crouch_repeats):
            add(f"crouch_{int(round(a)):03d}_{i + 1:02d}", "crouch",
                crouch_coordinates(sk, a, rate, crouch_duration, rng=rng), {"foot_angle_deg": float(a)})
    for r in functional_ranges:
        name = "functional_hip" if r == max(functional_ranges) else f"functional_hip_{int(round(r))}"
        add(name, "functional", functional_hip_coordinates(sk, r, rate, functional_time_scale, rng=rng),
            {"range_deg": float(r)})
    return sk, trials, stm


def _pose_columns(poses: dict) -> tuple[list[str], np.ndarray]:
    names, cols = [], []
    for seg, p in poses.items():
        for i, ax in enumerate("xyz"):
            names.append(f"{seg}_origin_{ax}")
            cols.append(p.origin[:, i])
        for i, ax in enumerate("xyz"):
            for j, c in enumerate("xyz"):
                names.append(f"{seg}_{ax}axis_{c}")
                cols.append(p.axes[:, j, i])
    return names, np.column_stack(cols)


def _lab_rotation(lab) -> np.ndarray:
    """Rotation from the phantom lab (X forward, Y left, Z up) to `lab` (a `phantoms.lab.Lab`)."""
    to_model = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])   # (fwd, left, up) -> (fwd, up, right)
    return lab.lab_from_model @ to_model


def write_trials(out_dir, ph, seed: int = 0, *, progress=None, lab=None, static_name: str = "static",
                 trial_format: str = "c3d", **kw) -> dict:
    """Write the motion phantom of `ph` into `out_dir` and return the entries for ``truth.json``.

    Files (lab frame: X forward, Y left, Z up):

    * ``static.c3d``, ``gait_NN.c3d``, ``crouch_AAA_NN.c3d`` (AAA = foot angle,
      degrees), ``functional_hip.c3d`` (largest range) and ``functional_hip_RR.c3d``:
      markers in mm (STA, noise, optional gaps);
    * ``truth/<trial>.mot``: true coordinates (rotations in degrees, translations
      in metres) incl. knee_flexion_r, knee_adduction_r, knee_rotation_r and
      knee_tx_r (anterior), knee_ty_r (proximal), knee_tz_r (lateral) in the
      femur frame;
    * ``truth/<trial>_angles.mot``: true Plug-in-Gait joint angles (degrees);
    * ``truth/<trial>_centres.trc``: true joint centres RHJC, LHJC, RKJC, LKJC, RAJC, LAJC (mm);
    * ``truth/<trial>_markers.trc``: the STA-free, noise-free marker centres (mm);
    * ``truth/<trial>_poses.sto``: true segment poses (origin m; axis unit vectors);
    * ``subject.json``: what the lab measures (leg lengths, knee/ankle widths,
      inter-ASIS distance, marker diameter, height, mass, tibial torsion; SI).

    Parameters
    ----------
    out_dir : folder (must exist; the caller stages it)
    ph : phantoms.anatomy.Phantom with both legs
    seed : int, seeds the motion, STA, noise and knee laws
    progress : callable(str) or None, called once per trial written
    lab : `phantoms.lab.Lab` or None: write every lab-frame file in that lab's axes (e.g. Y up, walking
        -x) instead of X forward, Y left, Z up
    static_name : file stem of the static trial (``Static`` as some labs write it)
    trial_format : ``c3d``, ``trc`` or ``both``
    **kw : passed to `make_trials` (rate, gait_trials, crouch_angles, sta, noise_sd, gaps, ...;
        ``functional_ranges=()`` writes no functional trial)

    Returns
    -------
    dict with ``knee_law_r``, ``knee_law_l`` (CorrelativeLaw.to_json schema) and ``motion``
    (lab frame, trials, STA amplitudes, noise).
    """
    from lowerlimb.atomic import inside, write_text
    from kinematics.io.c3d import write_c3d
    from kinematics.io.storage import write_mot, write_sto, write_trc

    out = Path(out_dir)
    if trial_format not in ("c3d", "trc", "both"):
        from lowerlimb.errors import InputError

        raise InputError("--format", f"{trial_format!r} is not one of c3d, trc, both")
    sk, trials, stm = make_trials(ph, seed, **kw)
    Rl = np.eye(3) if lab is None else _lab_rotation(lab)
    rot = lambda x: x @ Rl.T  # noqa: E731
    truth = inside(out, "truth")
    truth.mkdir(parents=True, exist_ok=True)
    coords = list(sk.coordinate_names)
    rotational = [c.name for c in sk.model.coordinates if c.kind == "rotational"]
    frame_text = "X forward, Y left, Z up" if lab is None else \
        f"{lab.name}: forward {lab.forward.tolist()}, up {lab.up.tolist()}, right {lab.lab_from_model[:, 2].tolist()}"
    centre_names = {"hip_r": "RHJC", "hip_l": "LHJC", "knee_r": "RKJC", "knee_l": "LKJC", "ankle_r": "RAJC", "ankle_l": "LAJC"}
    listing = []
    for tr in trials:
        stem = static_name if tr.kind == "static" else tr.name
        mk = MarkerTrial(tr.markers.names, rot(tr.markers.positions), tr.markers.rate, tr.time,
                         f"{stem}.c3d", tr.markers.extra)
        if trial_format in ("c3d", "both"):
            write_c3d(inside(out, f"{stem}.c3d"), mk)
        if trial_format in ("trc", "both"):
            write_trc(inside(out, f"{stem}.trc"), mk)
        st = sk.state(tr.q)
        write_mot(inside(truth, f"{tr.name}.mot"), coords, tr.time, tr.q, rotational=rotational)
        ang = sk.angles(st)
        vals = np.column_stack([ang[f"{j}_{s}"][:, k] for s in SIDES for j in ("hip", "knee", "ankle") for k in range(3)])
        write_mot(inside(truth, f"{tr.name}_angles.mot"), ANGLE_COLUMNS, tr.time, vals, rotational=ANGLE_COLUMNS,
                  name="PluginGaitAngles")
        c = sk.centres_lab(st)
        cn = list(centre_names.values())
        ct = MarkerTrial(tuple(cn), rot(np.stack([c[k] for k in centre_names], axis=1)), tr.markers.rate, tr.time,
                         f"{tr.name}_centres.trc")
        write_trc(inside(truth, f"{tr.name}_centres.trc"), ct)
        write_trc(inside(truth, f"{tr.name}_markers.trc"),
                  MarkerTrial(tr.markers.names, rot(tr.clean), tr.markers.rate, tr.time, f"{tr.name}_markers.trc"))
        from kinematics.gait.pig import SegmentPose

        poses = {k: SegmentPose(rot(v.origin), np.einsum("ij,fjk->fik", Rl, v.axes))
                 for k, v in sk.segment_poses(st).items()}
        pn, pv = _pose_columns(poses)
        write_sto(inside(truth, f"{tr.name}_poses.sto"), pn, tr.time, pv,
                  header_extra=[f"frame=lab ({frame_text}); origins in m; <seg>_<a>axis_<c> = component c of unit axis a"],
                  name="SegmentPoses")
        listing.append({"name": tr.name, "file": stem, "kind": tr.kind, "frames": int(tr.q.shape[0]), **tr.meta})
        if progress is not None:
            progress(tr.name)
    write_text(inside(out, "subject.json"), sk.subject.to_json() + "\n")
    motion = {
        "units": "m, rad", "lab_frame": frame_text + ("; lab = LAB_FROM_BODY @ body (phantoms.skeleton)" if lab is None
                                                      else "; lab = R @ (phantom lab: X forward, Y left, Z up)"),
        "lab": None if lab is None else {**lab.to_json(), "lab_from_phantom_lab": Rl.tolist()},
        "static_file": static_name, "format": trial_format,
        "rate_hz": float(trials[0].markers.rate), "trials": listing,
        "markers": list(trials[0].markers.names),
        "noise_sd_m": float(kw.get("noise_sd", 0.0005)),
        "soft_tissue_artefact": None if stm is None else {"amplitude_m": stm.amplitude,
                                                          "model": "linear in joint angles; see phantoms.motion"},
        "tibial_torsion_rad": {s: float(v) for s, v in sk.tibial_torsion.items()},
        "knee_translation_axes": "femur frame: knee_tx anterior, knee_ty proximal, knee_tz lateral",
    }
    return {"knee_law_r": sk.knee_laws["r"].to_json(), "knee_law_l": sk.knee_laws["l"].to_json(), "motion": motion}
