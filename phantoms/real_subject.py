"""A phantom subject folder on real anatomy: trials, markers, truth model and label volume.

`write_real_subject` writes what a gait lab and a radiology department hand
over for one subject whose skeleton is an expert-built model of real bones
(`phantoms.real_anatomy`), seen through any marker set
(`kinematics.io.marker_sets`), in any lab orientation (`phantoms.lab`), with
body-build soft tissue and palpation error (`phantoms.marker_placement`).

Motion (model coordinates, gait2392 names; the expert's joint axes):

* ``static``: standing as scanned (hip and knee angles of the scan pose, ankle
  and subtalar 0, the femurs vertical in the sagittal plane, the lowest foot
  point on the floor) for ``static_frames`` frames;
* ``gait_NN``: walking at 1.25 m/s on the normative curves of
  `phantoms.motion` (hip flexion relative to 10 deg of standing pelvic tilt,
  knee flexion 4-59 deg, ankle -16..10 deg), the left side half a cycle later;
* ``functional_hip`` (optional): star arcs of 40 deg, right hip then left hip.

In every frame the pelvis height puts the lowest point of the feet (convex
hulls of the calcaneus and toes meshes) on the floor, y = 0 (`on_the_floor`):
the stance foot rests on the floor, the swing foot clears it.

Markers: the placed sites (rigid on their bodies) plus a soft-tissue artefact
linear in the driving joint angles, as in `phantoms.motion` (segment amplitudes
over the reference excursions: thigh 10-20 mm, shank 5-15 mm, pelvis 4-6 mm,
foot 2-3 mm; bony markers 20-60 % of their segment's; a CAST plate moves
rigidly), and white noise.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from lowerlimb.errors import InputError
from lowerlimb.geometry import DEFAULT_MARKER_DIAMETER
from kinematics.io.marker_sets import MarkerDef, MarkerSet, resolve_marker_set
from kinematics.io.markers import MarkerTrial

from .lab import Lab, make_lab
from .marker_placement import PlacedMarker, place_markers
from .motion import star_arc
from .real_anatomy import RealAnatomy

__all__ = ["standing_coordinates", "coordinate_signs", "real_gait_coordinates", "real_functional_coordinates",
           "truth_model", "write_real_subject", "RealTrial", "make_real_trials"]

_X, _Y, _Z = np.eye(3)


def _fk(model, q):
    from kinematics.algorithms.fk import forward_kinematics

    return forward_kinematics(model, np.atleast_2d(q))


def _joint_origin(model, st, joint):
    j = next(jj for jj in model.joints if jj.name == joint)
    b = model.body_index(j.parent)
    return st.rotations[:, b] @ j.parent_offset.translation + st.positions[:, b]


def _foot_points(anat: RealAnatomy) -> list[tuple[int, np.ndarray]]:
    """(body index, convex-hull vertices in the body frame) of every foot bone (calcaneus, toes)."""
    key = "foot_hulls"
    if key not in anat._cache:
        out = []
        for bone in [b for b in anat.meshes if b.startswith(("calcn", "toes"))]:
            k = anat.model.body_index(anat.bone_body[bone])
            out.append((k, np.asarray(anat.local_meshes[bone].convex_hull.vertices)))
        anat._cache[key] = out
    return anat._cache[key]


def on_the_floor(anat: RealAnatomy, q: np.ndarray) -> np.ndarray:
    """Copy of q (F, n_q) with pelvis_ty shifted per frame so the lowest foot point is on the floor (y = 0).

    The stance foot then rests on the floor and the swing foot clears it: the pelvis's vertical motion
    follows from the legs (the model ground's Y is up).
    """
    st = _fk(anat.model, q)
    low = np.full(q.shape[0], np.inf)
    for k, V in _foot_points(anat):
        y = np.einsum("fj,pj->fp", st.rotations[:, k, 1, :], V) + st.positions[:, k, 1][:, None]
        low = np.minimum(low, y.min(axis=1))
    q = q.copy()
    q[:, anat.model.coordinate_index("pelvis_ty")] -= low
    return q


def standing_coordinates(anat: RealAnatomy) -> np.ndarray:
    """The standing pose (n_q,): scan-pose hip/knee angles, femurs vertical, feet on the floor (y = 0)."""
    m = anat.model
    q = anat.scan_q.copy()
    for i, n in enumerate(m.coordinate_names):
        if n.startswith(("ankle_", "subtalar_", "mtp_")):
            q[i] = 0.0
    it = m.coordinate_index("pelvis_tilt")
    for _ in range(3):
        st = _fk(m, q)
        d = np.mean([(_joint_origin(m, st, f"knee_{s}") - _joint_origin(m, st, f"hip_{s}"))[0] for s in anat.sides], axis=0)
        q[it] -= np.arctan2(d[0], -d[1])            # rotate about Z until hip -> knee points straight down
    return on_the_floor(anat, q[None])[0]


def coordinate_signs(anat: RealAnatomy, q0: np.ndarray) -> dict:
    """+1/-1 per coordinate kind so that a positive step is flexion, adduction, internal rotation, dorsiflexion.

    Found by finite differences of the model on the right (or first) side: hip flexion moves the knee
    centre forward, adduction medially, internal rotation turns the lateral epicondyle forward; knee
    flexion moves the ankle centre back; dorsiflexion lifts the toes.
    """
    m = anat.model
    s = anat.sides[0]
    lat = _Z if s == "r" else -_Z
    out = {}

    def moved(coord, point_fn):
        q = q0.copy()
        a = point_fn(_fk(m, q))
        q[m.coordinate_index(coord)] += 0.05
        return point_fn(_fk(m, q)) - a

    knee = lambda st: _joint_origin(m, st, f"knee_{s}")[0]  # noqa: E731
    ankle = lambda st: _joint_origin(m, st, f"ankle_{s}")[0]  # noqa: E731
    fem = m.body_index(f"femur_{s}")

    def lat_point(st):
        k = _joint_origin(m, st, f"knee_{s}")[0]
        R = st.rotations[0, fem]
        j = next(jj for jj in m.joints if jj.name == f"knee_{s}")
        ax = R @ j.parent_offset.rotation[:, 2]
        return k + 0.05 * (ax if ax @ lat > 0 else -ax)

    out["hip_flexion"] = np.sign(moved(f"hip_flexion_{s}", knee) @ _X)
    out["hip_adduction"] = np.sign(-(moved(f"hip_adduction_{s}", knee) @ lat))
    out["hip_rotation"] = np.sign(moved(f"hip_rotation_{s}", lat_point) @ _X)
    out["knee_angle"] = np.sign(-(moved(f"knee_angle_{s}", ankle) @ _X))
    # dorsiflexion: a point 10 cm in front of the ankle on the foot rises
    a0 = _joint_origin(m, _fk(m, q0), f"ankle_{s}")[0]
    st0 = _fk(m, q0)
    pf = m.body_index(f"calcn_{s}")
    loc = st0.rotations[0, pf].T @ (a0 + 0.1 * _X - st0.positions[0, pf])

    def fore(st):
        return st.rotations[0, pf] @ loc + st.positions[0, pf]

    out["ankle_angle"] = np.sign(moved(f"ankle_angle_{s}", fore) @ _Y)
    out["subtalar_angle"] = 1.0
    return {k: float(v) if v != 0 else 1.0 for k, v in out.items()}


#: m/s², the fore-aft acceleration amplitude of a walk's centre of mass (about 0.17 g: the braking and propulsive
#: ground reactions of 0.15-0.2 body weight at 1.2-1.4 m/s, Winter 2009, Biomechanics and Motor Control of
#: Human Movement, ch. 5); the walks of force-plate phantoms have it (`real_gait_coordinates` ``surge``)
WALK_SURGE = 1.7


def real_gait_coordinates(anat: RealAnatomy, q0: np.ndarray, signs: dict, rate: float, cycles: float = 2.0,
                          speed: float = 1.25, cycle_time: float = 1.1, rng=None,
                          smooth_hz: float | None = None, surge: float = 0.0) -> np.ndarray:
    """Walking (F, n_q) on `phantoms.motion`'s normative curves in the expert model's coordinates.

    `surge` (m/s²): amplitude of the pelvis's forward acceleration at twice the stride frequency, braking after
    each heel strike and propelling before the next, as the centre of mass of a walk does (about 0.15-0.2 g
    fore-aft; without it the pelvis keeps a constant speed and the momentum's ground reaction has no braking
    and propulsion).

    The pelvis height keeps the lowest foot point on the floor (`on_the_floor`); with `smooth_hz` it is
    then low-passed (2nd-order Butterworth, zero lag): the vertical ground reaction of the whole body's
    momentum stays within walking's 0.8-1.4 body weights instead of the spikes of a rigid foot roll-over
    (up to 4.7 BW), at the price of the stance foot sitting within about 1 cm of the floor (4 Hz).
    """
    from .motion import _GAIT, _periodic

    m = anat.model
    rng = rng or np.random.default_rng(0)
    F = max(int(round(cycles * cycle_time * rate)), 2)
    t = np.arange(F) / rate
    ph0 = rng.uniform(0, 1)
    q = np.repeat(q0[None], F, axis=0)
    ix = m.coordinate_index
    names = set(m.coordinate_names)
    for s, shift in (("r", 0.0), ("l", 0.5)):
        if f"hip_flexion_{s}" not in names:
            continue
        phase = t / cycle_time + ph0 + shift
        for key, coord, offset in (("hip_flexion", "hip_flexion", 10.0), ("hip_adduction", "hip_adduction", 0.0),
                                   ("hip_rotation", "hip_rotation", 0.0), ("knee_flexion", "knee_angle", 0.0),
                                   ("ankle_angle", "ankle_angle", 0.0), ("subtalar_angle", "subtalar_angle", 0.0)):
            name = f"{coord}_{s}"
            if name not in names:
                continue
            gain = rng.uniform(0.92, 1.08)
            curve = gain * _periodic(_GAIT[key], phase) - np.radians(offset)
            q[:, ix(name)] = q0[ix(name)] + signs[coord] * curve
    phase = t / cycle_time + ph0
    q[:, ix("pelvis_tilt")] += np.radians(1.5) * np.sin(4 * np.pi * phase)
    q[:, ix("pelvis_list")] += np.radians(4.0) * np.sin(2 * np.pi * phase)
    q[:, ix("pelvis_rotation")] += np.radians(5.0) * np.sin(2 * np.pi * phase + np.pi / 2)
    q[:, ix("pelvis_tx")] += speed * t
    if surge:
        w = 4.0 * np.pi / cycle_time
        q[:, ix("pelvis_tx")] += surge / w ** 2 * np.sin(4.0 * np.pi * phase)
    q[:, ix("pelvis_tz")] += 0.015 * np.sin(2 * np.pi * phase)
    q = on_the_floor(anat, q)
    if smooth_hz:
        from scipy.signal import butter, filtfilt

        b, a = butter(2, float(smooth_hz) / (0.5 * rate))
        q[:, ix("pelvis_ty")] = filtfilt(b, a, q[:, ix("pelvis_ty")], padtype="odd")
    return q


def real_functional_coordinates(anat: RealAnatomy, q0: np.ndarray, signs: dict, rate: float,
                                range_deg: float = 40.0) -> np.ndarray:
    """Star-arc hip calibration (Camomilla et al. 2006): 8 excursions then a circumduction, right then left."""
    m = anat.model
    R = np.radians(range_deg)
    n_out, n_circ = max(int(round(rate)), 4), max(int(round(2 * rate)), 8)
    flex, abd = star_arc(R, n_out, n_circ)
    n1 = flex.size
    q = np.repeat(q0[None], 2 * n1, axis=0)
    ix = m.coordinate_index
    for k, s in enumerate(anat.sides):
        sl = slice(k * n1, (k + 1) * n1)
        q[sl, ix(f"hip_flexion_{s}")] += signs["hip_flexion"] * flex
        q[sl, ix(f"hip_adduction_{s}")] -= signs["hip_adduction"] * abd
        q[sl, ix(f"knee_angle_{s}")] += signs["knee_angle"] * np.radians(10) * np.abs(flex) / R
    return on_the_floor(anat, q)


# --------------------------------------------------------------------------- truth model
#: segment mass fractions of body mass (de Leva 1996, J Biomech 29:1223, male); the pelvis body carries
#: the head, arms and trunk (the model has no torso), the foot's share is split talus 10 %, calcaneus 90 %
#: (or 75 % / 15 % toes with a toes body)
MASS_FRACTIONS = {"femur": 0.1416, "tibia": 0.0433, "foot": 0.0137}


def segment_bodies(anat: RealAnatomy, mass: float):
    """Bodies with `mass` (kg) distributed by `MASS_FRACTIONS`: com and inertia of each body's bone hull.

    The expert models' own mass properties are not usable (ICL-MRI's are mesh volumes in mm^3), so every
    body gets its share of the subject's mass, its centre of mass at the centroid of the convex hull of its
    bones and the hull's inertia at that mass (uniform density).
    """
    import trimesh

    from kinematics.multibody.model import Body

    m = anat.model
    has_toes = any(b.name.startswith("toes_") for b in m.bodies)
    frac = {}
    for b in m.bodies[1:]:
        base = b.name.split("_")[0]
        if base in ("femur", "tibia"):
            frac[b.name] = MASS_FRACTIONS[base]
        elif base in ("talus", "calcn", "toes"):
            share = {"talus": 0.10, "calcn": 0.75 if has_toes else 0.90, "toes": 0.15}[base]
            frac[b.name] = MASS_FRACTIONS["foot"] * share
    frac["pelvis"] = 1.0 - sum(frac.values())
    bodies = []
    for b in m.bodies[1:]:
        V = anat.body_vertices(b.name)
        if len(V) < 4:
            bodies.append(b)
            continue
        hull = trimesh.convex.convex_hull(V)
        mb = float(mass * frac.get(b.name, 0.0))
        I = hull.moment_inertia * (mb / hull.volume) if hull.volume > 0 else np.zeros((3, 3))
        bodies.append(Body(b.name, mb, np.asarray(hull.center_mass, float), I))
    return tuple(bodies)


def truth_model(anat: RealAnatomy, lab: Lab, placed: dict[str, PlacedMarker] | None = None, mass: float | None = None):
    """The truth skeleton with ground = the lab frame (ground_pelvis parent frame = `lab`) and the placed markers.

    With `mass` (kg) the bodies get `segment_bodies` mass properties.
    """
    from kinematics.multibody.joints import CustomJoint, Transform
    from kinematics.multibody.model import Marker

    m = anat.model
    if mass is not None:
        m = m.replace(bodies=segment_bodies(anat, mass))
    joints = []
    for j in m.joints:
        if j.parent == "ground":
            j = CustomJoint(j.name, j.parent, j.child, j.coordinates, Transform(lab.lab_from_model, lab.origin),
                            j.child_offset, rotations=j.rotations, translations=j.translations, kind_name="custom")
        joints.append(j)
    markers = tuple(Marker(p.label, p.body, np.asarray(p.offset, float)) for p in (placed or {}).values())
    return m.replace(joints=tuple(joints), markers=markers, gravity=-9.80665 * lab.up, name=m.name)


# --------------------------------------------------------------------------- soft-tissue artefact
_DRIVERS = {"pelvis": ("hip_flexion_r", "hip_flexion_l"),
            "femur": ("hip_flexion_{s}", "hip_adduction_{s}", "hip_rotation_{s}", "knee_angle_{s}"),
            "tibia": ("knee_angle_{s}", "ankle_angle_{s}"),
            "calcn": ("ankle_angle_{s}", "subtalar_angle_{s}"), "toes": ("ankle_angle_{s}", "subtalar_angle_{s}")}
_REF = {"hip_flexion": 0.6, "hip_adduction": 0.15, "hip_rotation": 0.3, "knee_angle": 1.05, "ankle_angle": 0.35,
        "subtalar_angle": 0.1}


def _sta_coefficients(anat, placed, q0, seed, scale):
    """Per marker: (driver columns, coefficients (3, k) m/rad in the body frame)."""
    from .motion import _AMPLITUDE

    m = anat.model
    rng = np.random.default_rng([int(seed), 11])
    groups: dict[str, list[PlacedMarker]] = {}
    for p in placed.values():
        groups.setdefault(p.body, []).append(p)
    out = {}
    amps = {}
    for body, ps in groups.items():
        key = body.split("_")[0]
        if key not in _DRIVERS:
            continue
        side = body[-1] if key != "pelvis" else ""
        drv = [d.format(s=side) for d in _DRIVERS[key] if d.format(s=side) in m.coordinate_names]
        k = len(drv)
        ref = np.array([_REF[d.rsplit("_", 1)[0]] for d in drv])
        g = rng.normal(size=(3, k)) * 0.01
        w = rng.normal(size=(3, k)) * 0.12
        pts = np.array([p.offset for p in ps])
        c = pts.mean(axis=0)
        amp = rng.uniform(*_AMPLITUDE["calcn" if key == "toes" else key]) * scale
        amps[body] = amp
        for p in ps:
            rigid = g + np.cross(w.T, p.offset - c).T
            e = np.zeros((3, k)) if p.kind == "cluster" else rng.normal(size=(3, k)) * 0.004
            C = rigid + e
            peak = np.linalg.norm(C * ref)
            lo, hi = (0.2, 0.6) if p.kind == "landmark" else (0.8, 1.0)
            f = rng.uniform(lo, hi) if p.kind != "cluster" else 1.0
            out[p.label] = ([m.coordinate_index(d) for d in drv], C * (amp * f / peak if peak > 0 else 0.0))
    return out, amps


# --------------------------------------------------------------------------- trials
class RealTrial:
    """One trial: name, kind, q (F, n_q), time (F,), markers (MarkerTrial, lab), clean (F, M, 3) lab."""

    def __init__(self, name, kind, q, time, markers, clean):
        self.name, self.kind, self.q, self.time, self.markers, self.clean = name, kind, q, time, markers, clean


def make_real_trials(anat: RealAnatomy, lab: Lab, placed: dict, q0, signs, seed: int, *, rate: float = 100.0,
                     gait_trials: int = 1, gait_cycles: float = 2.0, functional: bool = True, static_frames: int = 200,
                     sta: bool = True, sta_scale: float = 1.0, noise_sd: float = 0.0005,
                     static_only: tuple = (), smooth_hz: float | None = None, surge: float = 0.0) -> list[RealTrial]:
    """Static, gait and (optionally) functional trials of the placed markers (no file written)."""
    from kinematics.algorithms.fk import point_positions

    model = truth_model(anat, lab, placed)
    labels = [p for p in placed]
    bodies = np.array([model.body_index(placed[n].body) for n in labels])
    offs = np.array([placed[n].offset for n in labels])
    coefs, _ = _sta_coefficients(anat, placed, q0, seed, sta_scale) if sta else ({}, {})
    rng = np.random.default_rng([int(seed), 23])
    trials = []

    def add(name, kind, q):
        st = _fk(model, q)
        clean = point_positions(model, st, bodies, offs)
        pos = clean.copy()
        for j, n in enumerate(labels):
            if n in coefs:
                cols, C = coefs[n]
                local = (q[:, cols] - q0[cols]) @ C.T
                pos[:, j] += np.einsum("fij,fj->fi", st.rotations[:, bodies[j]], local)
        r2 = np.random.default_rng([int(seed), 29, len(trials)])
        if noise_sd > 0:
            pos = pos + r2.normal(scale=noise_sd, size=pos.shape)
        keep = [j for j, n in enumerate(labels) if kind == "static" or n not in static_only]
        names = tuple(labels[j] for j in keep)
        time = np.arange(q.shape[0]) / rate
        mt = MarkerTrial(names, pos[:, keep], float(rate), time, f"{name}", {"subject": f"phantom_{anat.name}_{seed}"})
        trials.append(RealTrial(name, kind, q, time, mt, clean[:, keep]))

    add("static", "static", np.repeat(q0[None], max(int(static_frames), 1), axis=0))
    for i in range(gait_trials):
        add(f"gait_{i + 1:02d}", "gait", real_gait_coordinates(anat, q0, signs, rate, gait_cycles, rng=rng,
                                                               smooth_hz=smooth_hz, surge=surge))
    if functional:
        add("functional_hip", "functional", real_functional_coordinates(anat, q0, signs, rate))
    return trials


def _save_truth_osim(model, anat: RealAnatomy, path: Path, geometry_dir: Path | None):
    from kinematics.io.opensim_io import import_opensim, to_opensim, write_osim

    om = to_opensim(model)
    if geometry_dir is not None:
        osim = import_opensim()
        bs = om.getBodySet()
        for bone, body in anat.bone_body.items():
            f = geometry_dir / f"{bone}.stl"
            if f.is_file():
                g = osim.Mesh(f"geometry/{bone}.stl")
                g.setName(bone)
                bs.get(body).attachGeometry(g)
    om.finalizeConnections()
    return write_osim(om, path)


def write_real_subject(out_dir, anat: RealAnatomy, *, marker_set="ior", lab: Lab | str = "y-up", walk: str = "+x",
                       build: str = "adult", seed: int = 0, voxel=(1e-3, 1e-3, 1e-3), noise: float = 0.0,
                       fibula_mesh: bool = True, labels: bool = True, meshes: bool = True, gait_trials: int = 1,
                       functional: bool = True, static_frames: int = 200, static_name: str = "static",
                       trial_format: str = "c3d", sta: bool = True, sta_scale: float = 1.0,
                       noise_sd: float = 0.0005, palpation: bool = True, rate: float = 100.0,
                       mesh_folder: str = "meshes", force_plates: bool = False,
                       progress: Callable[[str], None] | None = None) -> dict:
    """Write a real-anatomy phantom subject into `out_dir` (stage it with `lowerlimb.atomic.staged_dir`).

    Files: ``labels.nii.gz`` + ``label_map.json`` (voxelised meshes, scanner frame), ``meshes/<bone>.ply``
    (mm, scanner), trials ``<static_name>.c3d|.trc``, ``gait_NN``, ``functional_hip`` (lab frame, mm),
    ``markers.json`` (`kinematics.io.marker_sets`), ``subject.json`` (SI), ``truth_model.osim`` (ground = lab,
    the placed markers, ``geometry/<bone>.stl`` in body frames), ``truth.json`` (m) and ``truth/``
    (``<trial>.mot`` true coordinates and knee_flexion_<s>, ``<trial>_centres.trc`` true hip/knee/ankle centres,
    ``<trial>_markers.trc`` artefact-free noise-free markers; lab frame).

    Parameters
    ----------
    marker_set : preset name, markers.json path or `kinematics.io.marker_sets.MarkerSet`
    lab : `phantoms.lab.Lab` or ``"z-up"``/``"y-up"`` (with `walk`, e.g. ``"+x"``)
    build : ``child``, ``adult`` or ``obese`` (soft tissue, `phantoms.marker_placement`)
    fibula_mesh : write the fibula as its own bone; False: the fibula is a second component of the tibia
    trial_format : ``c3d``, ``trc`` or ``both``; static_name : stem of the static trial (``Static`` ...)
    static_frames : frames of the static trial; functional : write the functional hip trial
    mesh_folder : ``meshes`` (reference meshes beside a label volume) or ``bones`` (the subject's imaging IS a
        mesh folder, as `personalize run` reads it when there is no label volume)
    force_plates : add force platforms under the complete stance phases to the gait C3Ds
        (`phantoms.force_plates`; the gait's pelvis height is then smoothed at 4 Hz, see
        `real_gait_coordinates`); truth in ``truth/<trial>_grf.sto`` and truth.json ``force_plates``

    Returns
    -------
    dict: the truth.json content.
    """
    import trimesh

    from lowerlimb.atomic import inside, write_text
    from kinematics.io.c3d import write_c3d
    from kinematics.io.marker_sets import write_marker_set
    from kinematics.io.storage import write_mot, write_trc

    from .imaging import write_label_nifti, write_ply_mm
    from .real_anatomy import mesh_label_volume

    say = progress or (lambda m: None)
    if trial_format not in ("c3d", "trc", "both"):
        raise InputError("--format", f"{trial_format!r} is not one of c3d, trc, both")
    if not static_name or any(c in static_name for c in "/\\.") :
        raise InputError("--static-name", f"{static_name!r} is not a file stem")
    if not (1 <= int(static_frames) <= 100000):
        raise InputError("--static-frames", f"{static_frames} is outside 1-100000")
    out = Path(out_dir)
    lab = make_lab(lab, walk) if isinstance(lab, str) else lab
    ms = resolve_marker_set(marker_set)
    q0 = standing_coordinates(anat)
    signs = coordinate_signs(anat, q0)
    say("placing markers")
    placed, tissue = place_markers(anat, q0, ms, build, seed, palpation=palpation)
    if not placed:
        raise InputError("--marker-set", f"no marker of {ms.name!r} lies on a body of the model")
    static_only = tuple(k for k in placed if ms.markers[k].static_only)
    if force_plates and trial_format == "trc":
        raise InputError("--force-plates", "force platforms are written in C3D trials: use --format c3d or both")
    trials = make_real_trials(anat, lab, placed, q0, signs, seed, rate=rate, gait_trials=gait_trials,
                              functional=functional, static_frames=static_frames, sta=sta, sta_scale=sta_scale,
                              noise_sd=noise_sd, static_only=static_only, smooth_hz=4.0 if force_plates else None,
                              surge=WALK_SURGE if force_plates else 0.0)
    bmi = {"child": 17.0, "adult": 23.0, "obese": 34.0}[build]
    hip_knee = [np.linalg.norm(anat.joints_scanner[f"hip_{s}"][0] - anat.joints_scanner[f"knee_{s}"][0])
                for s in anat.sides]
    height = round(float(np.mean(hip_knee)) / 0.245, 3)     # femur length ~ 24.5 % of stature (Trotter & Gleser)
    body_mass = round(bmi * height**2, 1)
    model = truth_model(anat, lab, placed, mass=body_mass)
    # ---- imaging
    bones_out = {}
    for b, mesh in anat.meshes.items():
        if not fibula_mesh and b.startswith("fibula_"):
            continue
        if not fibula_mesh and b.startswith("tibia_"):
            fib = anat.meshes[f"fibula_{b[-1]}"]
            mesh = trimesh.util.concatenate([mesh, fib])
        bones_out[b] = mesh
    if labels:
        say("voxelising")
        lab_vol, affine, lmap = mesh_label_volume(bones_out, voxel=voxel, noise=noise, seed=seed,
                                                  progress=lambda b: say(f"voxelising {b}"))
        write_label_nifti(inside(out, "labels.nii.gz"), lab_vol, affine)
        write_text(inside(out, "label_map.json"), json.dumps(lmap, indent=1) + "\n")
    if meshes:
        for b, mesh in bones_out.items():
            write_ply_mm(inside(out, f"{mesh_folder}/{b}.ply"), mesh,
                         f"personalize real-anatomy phantom {anat.name} bone {b}\nunits mm\nframe scanner"
                         + (" (mirrored)" if b in anat.mirrored else ""))
    geo = inside(out, "geometry")
    geo.mkdir(parents=True, exist_ok=True)
    for b, mesh in anat.local_meshes.items():
        mesh.export(geo / f"{b}.stl")
    # ---- trials and truth
    truth_dir = inside(out, "truth")
    truth_dir.mkdir(parents=True, exist_ok=True)
    coords = list(model.coordinate_names)
    rot = [c.name for c in model.coordinates if c.kind == "rotational"]
    centre_names = {f"{j}_{s}": f"{s.upper()}{j[0].upper()}JC" for s in anat.sides for j in ("hip", "knee", "ankle")}
    listing = []
    plates_truth: dict = {}
    for tr in trials:
        stem = static_name if tr.kind == "static" else tr.name
        if trial_format in ("c3d", "both"):
            write_c3d(inside(out, f"{stem}.c3d"), tr.markers)
            if force_plates and tr.kind == "gait":
                from kinematics.io.storage import write_sto

                from .force_plates import add_force_plates, ground_reaction

                grf, cop, contact = ground_reaction(anat, model, tr.q, rate, lab)
                plates_truth[tr.name] = add_force_plates(inside(out, f"{stem}.c3d"), grf, cop, contact, lab, rate)
                cols = [f"{s}_ground_force_{k}{a}" for s in sorted(grf) for k in "vp" for a in "xyz"] + \
                    [f"{s}_contact" for s in sorted(grf)]
                write_sto(inside(truth_dir, f"{tr.name}_grf.sto"), cols, tr.time,
                          np.column_stack([grf[s] if k == "v" else cop[s] for s in sorted(grf) for k in "vp"]
                                          + [contact[s].astype(float) for s in sorted(grf)]),
                          header_extra=["frame=lab; per foot (l, r): force on the subject N, centre of pressure m, "
                                        "contact 1/0"], name="GroundReaction")
        if trial_format in ("trc", "both"):
            write_trc(inside(out, f"{stem}.trc"), tr.markers)
        # the model's coordinates, plus knee_flexion_<s> (flexion positive; not a model coordinate) so that
        # a pipeline naming knee flexion as Plug-in-Gait does can be compared
        kf = [f"knee_flexion_{s}" for s in anat.sides]
        kq = np.column_stack([signs["knee_angle"] * tr.q[:, model.coordinate_index(f"knee_angle_{s}")]
                              for s in anat.sides])
        write_mot(inside(truth_dir, f"{tr.name}.mot"), coords + kf, tr.time, np.column_stack([tr.q, kq]),
                  rotational=rot + kf)
        st = _fk(model, tr.q)
        cen = np.stack([_joint_origin(model, st, j) for j in centre_names], axis=1)
        write_trc(inside(truth_dir, f"{tr.name}_centres.trc"),
                  MarkerTrial(tuple(centre_names.values()), cen, tr.markers.rate, tr.time, "centres"))
        write_trc(inside(truth_dir, f"{tr.name}_markers.trc"),
                  MarkerTrial(tr.markers.names, tr.clean, tr.markers.rate, tr.time, "markers"))
        listing.append({"name": tr.name, "file": stem, "kind": tr.kind, "frames": int(tr.q.shape[0])})
        say(tr.name)
    _save_truth_osim(model, anat, inside(out, "truth_model.osim"), geo)
    written = MarkerSet(ms.name, {k: MarkerDef(ms.markers[k].segment if ms.markers[k].segment in model.body_names
                                               else placed[k].body, ms.markers[k].landmark, ms.markers[k].static_only)
                                  for k in placed})
    write_marker_set(inside(out, "markers.json"), written)
    # ---- what the lab measures (tape and calliper on the skin), SI
    st0 = _fk(model, q0)
    kjc = {s: _joint_origin(model, st0, f"knee_{s}")[0] for s in anat.sides}
    lms = {}
    from .marker_placement import find_landmarks

    for name, (bone, p) in find_landmarks(anat, q0).items():
        k = model.body_index(anat.bone_body[bone])
        lms[name] = st0.rotations[0, k] @ p + st0.positions[0, k]
    subject = {"units": "m, kg"}
    for s, side in (("r", "right"), ("l", "left")):
        if s not in anat.sides:
            continue
        P = s.upper()
        subject[f"{side}_leg_length"] = float(np.linalg.norm(lms[f"{P}ASI"] - kjc[s]) + np.linalg.norm(kjc[s] - lms[f"{P}MMA"]) + 0.01)
        subject[f"{side}_knee_width"] = float(np.linalg.norm(lms[f"{P}KNE"] - lms[f"{P}MFC"]) + 2 * tissue.get(f"{P}KNE", 0.005))
        subject[f"{side}_ankle_width"] = float(np.linalg.norm(lms[f"{P}ANK"] - lms[f"{P}MMA"]) + 2 * tissue.get(f"{P}ANK", 0.003))
    subject.update({"inter_asis_distance": float(np.linalg.norm(lms["RASI"] - lms["LASI"])),
                    "marker_diameter": DEFAULT_MARKER_DIAMETER, "height": height, "mass": body_mass})
    write_text(inside(out, "subject.json"), json.dumps(subject, indent=1) + "\n")
    # ---- truth.json
    joints = {k: {"origin": o.tolist(), "rotation": R.tolist()} for k, (o, R) in anat.joints_scanner.items()}
    truth = {
        "units": "m, rad", "kind": "real-anatomy phantom",
        "anatomy": {"name": anat.name, **anat.sources, "mirrored_bones": list(anat.mirrored),
                    "mirroring": None if anat.symmetry is None else {
                        "how": "pelvis symmetry S(x) = M x + c: reflection about the expert pelvis frame's "
                               "sagittal plane refined by ICP of the mirrored pelvis onto itself",
                        "M": anat.symmetry[0].tolist(), "c": anat.symmetry[1].tolist()},
                    "fibula": anat.fibula_from, "fibula_mesh_written": bool(fibula_mesh),
                    "bone_body": anat.bone_body},
        "joints": {"frame": "scanner (scan pose); rotation columns X, Y, Z; Z = the joint's flexion axis",
                   "joints": joints},
        "image": {"file": "labels.nii.gz" if labels else None, "voxel_m": list(map(float, np.broadcast_to(voxel, 3))),
                  "noise": float(noise), "noise_seed": int(seed), "affine_units": "mm",
                  "meshes": f"{mesh_folder}/<bone>.ply in mm, scanner frame" if meshes else None},
        "lab": lab.to_json(),
        "model": {"file": "truth_model.osim", "ground": "lab frame", "coordinates": coords,
                  "standing_q": dict(zip(coords, map(float, q0))), "signs": signs,
                  "scan_q": dict(zip(coords, map(float, anat.scan_q)))},
        "marker_set": ms.name,
        "tissue": {"build": build, "thickness_m": tissue, "model": "phantoms.marker_placement.TISSUE_CLASSES"},
        "markers": {k: {**p.to_json(), "segment": written.markers[k].segment,
                        "static_only": written.markers[k].static_only} for k, p in placed.items()},
        "landmarks_lab_standing_m": {k: v.tolist() for k, v in lms.items()},
        "force_plates": plates_truth or None,
        "motion": {"rate_hz": float(rate), "trials": listing, "functional_trial": bool(functional),
                   "static_frames": int(static_frames), "format": trial_format, "static_file": static_name,
                   "noise_sd_m": float(noise_sd), "soft_tissue_artefact": bool(sta), "sta_scale": float(sta_scale),
                   "palpation": bool(palpation)},
    }
    write_text(inside(out, "truth.json"), json.dumps(truth, indent=1) + "\n")
    return truth
