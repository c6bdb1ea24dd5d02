"""The personalised muscles against gait2392 scaled to the same subject by OpenSim's ScaleTool (issue M1's
benchmark).

`scale_generic`: OpenSim's ScaleTool (ModelScaler only) on the generic model, with virtual markers: the
subject's bony landmarks (a phantom's truth) and the same landmarks detected on gait2392's own bones, so that
the two marker sets mean the same points (gait2392's scale marker set places its skin markers by its own
protocol: R.ASIS 9 mm lateral of its bony ASIS, Toe.Tip beyond the toes; scaling a subject's skin markers
against it scales the pelvis by 0.74 on the ICL-MRI phantom whose bony ASIS distance is 0.84 of gait2392's).
Measurement pairs after OpenSim's example (``subject01_Setup_Scale.xml``, `MEASUREMENTS`); each body scaled
uniformly; the torso is not scaled (no head marker on a lower-limb subject).

`compare_models`: sweeps of one generic coordinate at a time, the others at zero (hip flexion -20..60 deg, knee
flexion 0..90 deg, i.e. ``knee_angle`` 0..-90, ankle -20..20 deg), each pose carried to the personalised model
by the `poses.CoordinateMap` (the same anatomical posture).  Per muscle:

* MTU length error: ``max_q |L_p(q) - L_s(q)| / L_s(q)`` over every pose of the three sweeps (p: personalised,
  s: scaled gait2392);
* moment arm about the swept coordinate, ``r = -dL/dq`` (central differences, ``h = 1e-3 rad``, one-sided beside
  a conditional path point's switch, `_moment_arms`; the
  personalised model's about the same generic coordinate, so signs compare): the normalised RMS error
  ``sqrt(mean (r_p - r_s)²) / sqrt(mean r_s²)``, for the muscles whose scaled moment arm about that coordinate
  reaches `MIN_MOMENT_ARM` somewhere in the sweep (the muscles that cross the joint).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["scale_generic", "compare_models", "compare_run", "table", "worst", "generic_virtual_markers", "SWEEPS", "TOLERANCE", "MIN_MOMENT_ARM"]

#: generic coordinate base name -> (first, last) degrees of the sweep
SWEEPS = {"hip_flexion": (-20.0, 60.0), "knee_angle": (0.0, -90.0), "ankle_angle": (-20.0, 20.0)}
TOLERANCE = 0.15
#: a muscle's moment arm about a coordinate counts when it reaches this somewhere in the sweep (m)
MIN_MOMENT_ARM = 0.005
_H = 1e-3

#: measurement -> (marker pairs, bodies scaled): OpenSim's example pairs on bony landmarks, the thigh between
#: two femoral landmarks (greater trochanter, lateral epicondyle) rather than from the pelvis's ASIS
MEASUREMENTS = {"pelvis": ([("RASI", "LASI"), ("RASI", "RPSI"), ("LASI", "LPSI")], ["pelvis"]),
                "thigh": ([("RTRO", "RKNE"), ("LTRO", "LKNE")], ["femur_r", "femur_l"]),
                "shank": ([("RKNE", "RANK"), ("LKNE", "LANK")], ["tibia_r", "tibia_l", "talus_r", "talus_l"]),
                "foot": ([("RHEE", "RD1M"), ("RHEE", "RD5M"), ("LHEE", "LD1M"), ("LHEE", "LD5M")],
                         ["calcn_r", "calcn_l", "toes_r", "toes_l"])}
#: generic bone -> body its landmarks ride on (the fibula's on the tibia)
_LANDMARK_BODIES = {"pelvis": "pelvis", "femur_r": "femur_r", "tibia_r": "tibia_r", "fibula_r": "tibia_r",
                    "calcn_r": "calcn_r"}


def generic_virtual_markers(generic) -> dict:
    """Bony landmarks of gait2392's own bones (`personalize.landmarks.detect_landmarks` on its meshes): name ->
    (body, (3,) m in the body frame); the left side mirrored from the right (z -> -z), as gait2392's left bones
    are."""
    from personalize.landmarks import detect_landmarks

    ls = detect_landmarks({"pelvis": generic.meshes["pelvis"], "femur_r": generic.meshes["femur_r"],
                           "tibia_r": generic.meshes["tibia_r"], "calcn_r": generic.meshes["calcn_r"]},
                          trust_names=True)
    out = {}
    names = {n for pairs, _ in MEASUREMENTS.values() for p in pairs for n in p}
    for bone, res in ls.bones.items():
        body = _LANDMARK_BODIES.get(bone)
        for n, lm in res.landmarks.items():
            if body is None or n not in names:
                continue
            x = np.asarray(lm.position, float)
            out[n] = (body, x)
            if body != "pelvis" and n.startswith("R"):
                out["L" + n[1:]] = (body[:-1] + "l", x * [1.0, 1.0, -1.0])
    return out


def scale_generic(generic, subject_markers: dict, mass: float, work: Path, measurements: dict | None = None):
    """gait2392 scaled by OpenSim's ScaleTool (ModelScaler) to the subject's virtual markers: opensim.Model.

    generic : `GenericModel`; subject_markers : landmark name -> (3,) m (any one frame: only distances count),
    e.g. a phantom's ``truth.json`` ``landmarks_lab_standing_m``; the model's markers are the same landmarks
    detected on gait2392's bones (`generic_virtual_markers`).  Each body is scaled uniformly by the mean ratio of
    its measurement's pair distances (`MEASUREMENTS`, pairs with both markers on both sides only).  `work` :
    folder for the tool's files (setup, virtual trial, models); measurements : measurement -> (marker pairs,
    bodies), default `MEASUREMENTS`.
    """
    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    gm = generic_virtual_markers(generic)
    model = osim.Model(os.fspath(generic.path))
    for n, (body, x) in sorted(gm.items()):
        model.addMarker(osim.Marker(n, model.getBodySet().get(body), osim.Vec3(*x)))
    model.finalizeConnections()
    model.printToXML(os.fspath(work / "gait2392_virtual_markers.osim"))
    labels = sorted(set(gm) & set(subject_markers))
    rows = "\n".join(f"{i + 1}\t{0.01 * i:.3f}\t" + "\t".join(f"{1e3 * v:.4f}" for n in labels
                                                           for v in np.asarray(subject_markers[n], float))
                     for i in range(2))
    trc = ("PathFileType\t4\t(X/Y/Z)\tvirtual.trc\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\t"
           "OrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
           f"100\t100\t2\t{len(labels)}\tmm\t100\t1\t2\n"
           "Frame#\tTime\t" + "\t\t\t".join(labels) + "\n\t\t"
           + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(len(labels))) + "\n\n" + rows + "\n")
    (work / "virtual.trc").write_text(trc, encoding="utf-8")
    meas = []
    for name, (pairs, bodies) in (MEASUREMENTS if measurements is None else measurements).items():
        pairs = [p for p in pairs if set(p) <= set(labels)]
        if not pairs:
            continue
        mp = "".join(f"<MarkerPair><markers> {a} {b} </markers></MarkerPair>" for a, b in pairs)
        bs = "".join(f'<BodyScale name="{b}"><axes> X Y Z </axes></BodyScale>' for b in bodies)
        meas.append(f'<Measurement name="{name}"><apply>true</apply><MarkerPairSet><objects>{mp}</objects>'
                    f'</MarkerPairSet><BodyScaleSet><objects>{bs}</objects></BodyScaleSet></Measurement>')
    out_model = work / "gait2392_scaled.osim"
    setup = f"""<?xml version="1.0" encoding="UTF-8"?>
<OpenSimDocument Version="40000"><ScaleTool name="gait2392_scaled"><mass>{float(mass)}</mass>
<GenericModelMaker><model_file>gait2392_virtual_markers.osim</model_file></GenericModelMaker>
<ModelScaler><apply>true</apply><scaling_order> measurements </scaling_order>
<MeasurementSet><objects>{''.join(meas)}</objects></MeasurementSet>
<marker_file>virtual.trc</marker_file><time_range> 0 0.01 </time_range>
<preserve_mass_distribution>true</preserve_mass_distribution><output_model_file>{out_model.name}</output_model_file>
</ModelScaler><MarkerPlacer><apply>false</apply></MarkerPlacer></ScaleTool></OpenSimDocument>
"""
    (work / "scale_setup.xml").write_text(setup, encoding="utf-8")
    if out_model.exists():
        out_model.unlink()
    tool = osim.ScaleTool(os.fspath(work / "scale_setup.xml"))
    tool.run()                               # False without a marker placer, though the model is written
    if not out_model.is_file():
        raise RuntimeError("OpenSim's ScaleTool failed")
    out = osim.Model(os.fspath(out_model))
    out.initSystem()
    return out


def _sweep_poses(side: str, n: int) -> list[tuple[str, float]]:
    # cell mid-points: no sample on a conditional path point's switch (gait2392's sit on round angles)
    u = (np.arange(n) + 0.5) / n + 0.0137          # off round angles
    return [(f"{c}_{side}", np.radians(a + (b - a) * v)) for c, (a, b) in SWEEPS.items() for v in u]


#: m, one-sided moment arms further apart than this straddle a jump of the path (a conditional path point switching
#: between q - h and q + h); a smooth path's differ by about 2 h |d²L/dq²|, under 0.1 mm
_JUMP = 0.005


def _moment_arms(L: np.ndarray) -> np.ndarray:
    """Moment arms ``-dL/dq`` from rows (q, q - h, q + h) of MTU lengths (n_poses x 3, n_muscles): the central
    difference, or the one-sided difference of smaller magnitude where the two sides disagree by more than
    `_JUMP` (the other side spans a conditional path point's switch, where the length jumps)."""
    L0, Lm, Lp = L[0::3], L[1::3], L[2::3]
    left, right = -(L0 - Lm) / _H, -(Lp - L0) / _H
    central = 0.5 * (left + right)
    jump = np.abs(right - left) > _JUMP
    return np.where(jump, np.where(np.abs(left) < np.abs(right), left, right), central)


def compare_models(personal, scaled, cmap, muscles, sides=("r",), n: int = 9) -> dict:
    """Per-muscle errors of the personalised model against the scaled gait2392 (module docstring).

    personal, scaled : opensim.Model with the muscles; cmap : `poses.CoordinateMap`; muscles : names; n : poses
    per sweep.  Returns {"muscles": name -> {"length": err, "<coordinate>": err or None}, "fractions": {"length" |
    "<coordinate base>": fraction within `TOLERANCE`}, "counts": {...: muscles counted}}.
    """
    from .calibration import mtu_lengths

    rows: dict = {}
    for s in sides:
        mus = [m for m in muscles if m.endswith(f"_{s}")]
        plan = _sweep_poses(s, n)
        gposes = []
        for coord, q in plan:
            gposes += [{coord: q}, {coord: q - _H}, {coord: q + _H}]
        Ls = mtu_lengths(scaled, mus, gposes)
        Lp = mtu_lengths(personal, mus, [cmap.subject_pose(p) for p in gposes])
        Ls0, Lp0 = Ls[0::3], Lp[0::3]
        rs, rp = _moment_arms(Ls), _moment_arms(Lp)
        names = np.array([c for c, _ in plan])
        for k, m in enumerate(mus):
            row = {"length": float(np.max(np.abs(Lp0[:, k] - Ls0[:, k]) / Ls0[:, k]))}
            for c in SWEEPS:
                sel = names == f"{c}_{s}"
                a, b = rs[sel, k], rp[sel, k]
                row[c] = (float(np.sqrt(np.mean((b - a) ** 2)) / np.sqrt(np.mean(a**2)))
                          if np.max(np.abs(a)) >= MIN_MOMENT_ARM else None)
                row[f"{c}_mm"] = (round(1e3 * float(np.max(np.abs(a))), 1), round(1e3 * float(np.max(np.abs(b))), 1))
            rows[m] = row
    fractions, counts = {}, {}
    for key in ("length", *SWEEPS):
        v = [r[key] for r in rows.values() if r[key] is not None]
        counts[key] = len(v)
        fractions[key] = float(np.mean(np.asarray(v) <= TOLERANCE)) if v else float("nan")
    return {"muscles": rows, "fractions": fractions, "counts": counts, "tolerance": TOLERANCE}


def compare_run(model_dir: str | os.PathLike, subject_dir: str | os.PathLike, work: str | os.PathLike,
                n: int = 9, sides=("r",)) -> dict:
    """`compare_models` on a pipeline output (``model.osim`` with its muscles, ``muscles.json``) against gait2392
    scaled to the phantom subject's virtual markers (``truth.json``'s ``landmarks_lab_standing_m``)."""
    import json

    from kinematics.io.opensim_io import import_opensim

    from .generic import load_generic_model
    from .poses import CoordinateMap

    osim = import_opensim()
    model_dir, subject_dir = Path(model_dir), Path(subject_dir)
    rep = json.loads((model_dir / "muscles.json").read_text(encoding="utf-8"))
    truth = json.loads((subject_dir / "truth.json").read_text(encoding="utf-8"))
    subj = json.loads((subject_dir / "subject.json").read_text(encoding="utf-8")) \
        if (subject_dir / "subject.json").is_file() else {}
    personal = osim.Model(os.fspath(model_dir / "model.osim"))
    personal.initSystem()
    generic = load_generic_model(rep["generic_model"])
    scaled = scale_generic(generic, truth["landmarks_lab_standing_m"], float(subj.get("mass") or 75.0), Path(work))
    c = rep["coordinates"]
    cmap = CoordinateMap({g: (v["subject"], v["sign"], v["offset"]) for g, v in c["coordinates"].items()}, c["held"])
    return compare_models(personal, scaled, cmap, rep["muscles"], sides, n=n)


def table(result: dict) -> str:
    """Plain-text table of `compare_models`' result: one row per muscle, then the fractions within tolerance."""
    cols = ("length", *SWEEPS)
    head = f"{'muscle':14s} " + " ".join(f"{c:>12s}" for c in cols)
    lines = [head, "-" * len(head)]
    for m, r in result["muscles"].items():
        lines.append(f"{m:14s} " + " ".join(f"{'-' if r[c] is None else f'{100 * r[c]:.1f} %':>12s}" for c in cols))
    lines.append("-" * len(head))
    lines.append(f"{'within ' + format(100 * result['tolerance'], '.0f') + ' %':14s} "
                 + " ".join(f"{100 * result['fractions'][c]:>10.0f} %" for c in cols))
    lines.append(f"{'muscles':14s} " + " ".join(f"{result['counts'][c]:>12d}" for c in cols))
    return "\n".join(lines)


def worst(result: dict, k: int = 5) -> dict:
    """The `k` muscles farthest from the reference per measure: measure -> [(muscle, error), ...] (largest first)."""
    out = {}
    for key in ("length", *SWEEPS):
        v = sorted(((m, r[key]) for m, r in result["muscles"].items() if r[key] is not None), key=lambda x: -x[1])
        out[key] = v[:k]
    return out
