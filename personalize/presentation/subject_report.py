"""The report of one subject's run (``report.html``): estimates per source, fusion weights, IK residuals, bones.

Also the page a refused subject gets instead (`write_refusal_report`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from lowerlimb.atomic import inside
from lowerlimb.errors import FitError, InputError

__all__ = ["write_subject_report", "write_refusal_report"]


def write_subject_report(path: Path, summary, ik: dict, bones) -> None:
    """``report.html`` of a run: `personalize.pipeline.SubjectSummary`, the IK results (trial -> result) and the
    `personalize.bone_set.BoneSet` (surfaces and landmarks, pictured per bone)."""
    from .gait_plots import SIDE_COLOURS
    from .html_report import Figure, Section, Table, new_figure, render_report

    est, ls, surfaces = summary.estimates, bones.landmarks, bones.surfaces
    rows = []
    for s in est.centres:
        for jn, e in est.centres[s].items():
            for src, g in (("mri", e.mri), ("motion", e.motion)):
                rows.append([f"{jn}_{s} centre", src, *(1e3 * g.mean).round(1).tolist(), float(1e3 * g.rms_sd), ""])
            f = e.fused
            rows.append([f"{jn}_{s} centre", "fused", *(1e3 * f.mean).round(1).tolist(), float(1e3 * np.sqrt(np.trace(f.cov) / 3)),
                         f"mri {f.shares[0]:.2f} / motion {f.shares[1]:.2f}; chi2 p={f.p_value:.2g}"])
    t_centres = Table(["joint", "source", "x (mm)", "y (mm)", "z (mm)", "sd (mm)", "weights"], rows,
                      caption="Joint centres, static-trial lab frame (X forward, Y left, Z up)")
    arows = []
    for s in est.axes:
        for jn, e in est.axes[s].items():
            for src, d in (("mri", e.mri), ("motion", e.motion)):
                u = np.asarray(d.direction) / np.linalg.norm(d.direction)
                arows.append([f"{jn}_{s} axis", src, *u.round(4).tolist(), float(d.sd_deg), ""])
            f = e.fused
            arows.append([f"{jn}_{s} axis", "fused", *f.direction.round(4).tolist(), float(f.sd_deg),
                          f"mri {f.shares[0]:.2f} / motion {f.shares[1]:.2f}"])
    t_axes = Table(["axis", "source", "x", "y", "z", "sd (deg)", "weights"], arows, caption="Joint axes (unit vectors, static lab frame)")
    sections = [Section("Subject", [f"Folder: {summary.subject_dir}", f"Sides: {', '.join(summary.sides)}",
                                    f"Trials: {', '.join(summary.trials)}"] + list(summary.notes))]
    est_items = [t_centres, t_axes]
    if est.hip_joint is not None:
        hj = est.hip_joint
        est_items.insert(1, "Hip centres are fused jointly (generalised least squares): both MRI hips share the pelvis "
                            "registration error, so each functional centre also corrects the other hip. Weights (share of "
                            "the 6-vector's information): " + ", ".join(f"{n} {w:.2f}" for n, w in zip(hj.names, hj.shares))
                         + f"; agreement χ² = {hj.chi2:.1f} ({hj.dof} dof, p = {hj.p_value:.2g}). MRI hip covariance = "
                           f"registration covariance x {est.mri_hip_scale:g}; SCoRE covariance includes the soft-tissue-"
                           "artefact term (both calibrated on training phantoms).")
    if est.skin:
        srows = [[k, round(v.thickness * 1e3, 1), round(v.sd * 1e3, 1), v.source, v.note or "-"] for k, v in est.skin.items()]
        est_items.append("Soft tissue under the pelvic markers (skin-to-bone distance along the bone's outward normal): "
                         "measured in the MRI's body/skin label where plausible, else the population prior "
                         "(Mantovani et al. 2016). The measured sd includes an assumed 2 mm for supine scan vs "
                         "standing with a taped marker.")
        est_items.append(Table(["marker", "thickness (mm)", "sd (mm)", "source", "note"], srows,
                               caption="Soft tissue used by the pelvis registration"))
    lrows = []
    for s, k in summary.intercepts.items():
        f = k.fused
        lrows.append([f"knee_{s}_standing_translation", "0 / 0 / 0", "", " / ".join(f"{1e3 * x:+.1f}" for x in k.motion.mean),
                      "", " / ".join(f"{1e3 * x:+.2f}" for x in f.mean), round(1e3 * float(np.mean(f.sd)), 2),
                      f"mri {f.shares[0]:.2f} / motion {f.shares[1]:.2f}"])
    for name, v in summary.lengths.items():
        f = v.fused
        lrows.append([name, round(1e3 * float(v.mri.mean[0]), 1), round(1e3 * float(v.mri.sd[0]), 2),
                      round(1e3 * float(v.motion.mean[0]), 1), round(1e3 * float(v.motion.sd[0]), 2),
                      round(1e3 * float(f.mean[0]), 1), round(1e3 * float(f.sd[0]), 2),
                      f"mri {f.shares[0]:.2f} / motion {f.shares[1]:.2f}"])
    if lrows:
        est_items.append(Table(["parameter", "MRI (mm)", "MRI sd", "motion (mm)", "motion sd", "fused (mm)", "fused sd",
                                "weights"], lrows,
                               caption="Segment lengths (frame-free) and the knee law's intercept (standing knee "
                                       "translation tx / ty / tz, knee frame), fused as Gaussians"))
    sections.append(Section("Per-joint estimates: MRI, motion and fused", est_items))
    cb = summary.chain_blend
    if cb.get("median_foot_to_hip_weight"):
        segs = ("femur_r", "tibia_r", "foot_r", "femur_l", "tibia_l", "foot_l")
        crow = [[t, *(round(w.get(g, float("nan")), 2) for g in segs)] for t, w in cb["median_foot_to_hip_weight"].items()]
        items = ["Each segment's pose is blended frame by frame from the hip-first (Plug-in-Gait) and the foot-first "
                 "(Tändl et al.) chains with Gaussian weights from each chain's rigid marker residual on that segment "
                 "(kinematics/<trial>_chains.mot, _chain_weights.sto)."]
        items.append(Table(["trial", *segs], crow, caption="Median weight of the foot-to-hip chain"))
        if "angle_rmse_deg_mean_over_angles" in cb:
            items.append("Gait trials, angle RMSE against the truth averaged over the 18 Plug-in-Gait angles: "
                         + ", ".join(f"{m} {v:.2f} deg" for m, v in cb["angle_rmse_deg_mean_over_angles"].items()))
        sections.append(Section("Hip-first and foot-first chains, blended per frame", items))
    if summary.truth is not None:
        errors = summary.truth.to_json()["errors"]
        er = [[k, *(round(v[s], 2) for s in ("mri", "motion", "fused"))] for k, v in errors.items()]
        sections.append(Section("Errors against the phantom truth (worst side)",
                                [Table(["quantity", "MRI", "motion", "fused"], er)]))
    reg_rows = [[k, r.rms * 1e3, float(np.max(r.rotation_sd_deg)), ", ".join(r.names), ", ".join(r.rejected) or "-"]
                for k, r in est.registrations.items()]
    sections.append(Section("Registration (MRI -> static markers)",
                            [Table(["segment", "rms (mm)", "max rotation sd (deg)", "used", "rejected"], reg_rows)]))
    ik_rows = [[k, v.rms_mean_mm, v.rms_max_mm, v.frames, v.worst_marker] for k, v in summary.ik.items()]
    items = [Table(["trial", "mean RMS (mm)", "max RMS (mm)", "frames", "worst marker (mean error)"], ik_rows,
                   caption="Marker residuals of the personalised model's IK")]
    name = next((k for k in ik if k.startswith("gait")), next((k for k in ik if k != "static"), next(iter(ik))))
    res = ik[name]
    fig = new_figure(12, 3.2)
    axs = fig.subplots(1, 3)
    for ax, jn in zip(axs, ("hip_flexion", "knee_flexion", "ankle_angle")):
        for s in est.centres:
            c = f"{jn}_{s}"
            if c in res.coordinates:
                ax.plot(res.time, np.degrees(res.q[:, res.coordinates.index(c)]), label=s,
                        color=SIDE_COLOURS.get(s[-1].upper()))
        ax.set_title(jn)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("deg (hip, knee: anatomical; others: 0 = static pose)")
        ax.legend()
    fig.tight_layout()
    items.append(Figure(fig, caption=f"{name}: joint angles of the personalised model"))
    fig = new_figure(12, 3.2)
    ax = fig.subplots()
    me = np.nanmean(res.marker_errors, axis=0) * 1e3
    ax.bar(np.arange(len(me)), me)
    ax.set_xticks(np.arange(len(me)), res.markers, rotation=90, fontsize=7)
    ax.set_ylabel("mean error (mm)")
    fig.tight_layout()
    items.append(Figure(fig, caption=f"{name}: mean marker residual per marker (soft-tissue artefact and noise)"))
    sections.append(Section("Inverse kinematics", items))
    if summary.generic:
        sections.append(_generic_section(summary.generic, path.parent, ik, list(est.centres)))
    if summary.patellofemoral:
        sections.append(_patella_section(summary.patellofemoral))
    pics = []
    from ..landmarks.plot import plot_bone

    for bone in ("pelvis", "femur_r", "tibia_r", "femur_l"):
        if bone in surfaces and bone in ls.bones:
            tmp = path.parent / f".{bone}_landmarks.png"
            plot_bone(surfaces[bone].mesh, ls.bones[bone], tmp)
            pics.append(Figure(tmp.read_bytes(), caption=f"{bone}: surface and detected landmarks (scanner frame, mm)"))
            tmp.unlink()
    if pics:
        sections.append(Section("Bones and landmarks", pics))
    render_report(path, f"Personalised model: {summary.subject}", sections,
                  meta="units: m, mm in tables as stated; frame: lab of the static trial")


def write_refusal_report(out: Path, subject_dir, exc: BaseException) -> None:
    """`out` replaced by a folder holding only ``report.html`` of the refused subject: the error, what a subject folder holds."""
    from ..outputs import replaced_dir

    kind = ("Input error" if isinstance(exc, InputError) else "Estimation error" if isinstance(exc, FitError)
            else "Internal error")
    text = str(exc) if isinstance(exc, (InputError, FitError)) else f"{type(exc).__name__}: {exc}"
    with replaced_dir(out) as stage:
        _refusal_page(stage, subject_dir, kind, text)


def _refusal_page(stage: Path, subject_dir, kind: str, text: str) -> None:
    from .html_report import Section, render_report

    render_report(inside(stage, "report.html"), f"Personalised model: {Path(subject_dir).name} refused", [
        Section(kind, [" ".join(text.split()), "The subject was refused: no model, kinematics or summary.json was written."]),
        Section("What a subject folder holds", [
            "labels.nii.gz (+ label_map.json) or bones/; static.c3d; at least one motion trial C3D "
            "(functional_hip*.c3d calibrates the hip centres); subject.json (height, mass, Plug-in-Gait "
            "measurements). Every trial must be of the same subject (same pelvis marker distances) and the "
            "labels and markers must share a side."])],
        meta="units: none; frame: none")


def _generic_section(generic: dict, folder: Path, ik: dict, sides: list):
    """The personalised model beside gait2392 scaled to the same markers (summary.json's ``generic``): joint
    centres, per-trial residuals and angle differences, and the sagittal angles of one gait trial, both models."""
    from kinematics.io.storage import read_mot

    from .gait_plots import SIDE_COLOURS
    from .html_report import Figure, Section, Table, new_figure

    truth = generic.get("truth") or {}
    err = truth.get("centre_error_mm", {})
    crow = [[j, round(v["distance_mm"], 1), *((round(err[j]["personalised"], 1), round(err[j]["generic"], 1))
                                               if j in err else (("-", "-") if truth else ()))]
            for j, v in generic["centres"].items()]
    head = ["joint", "distance (mm)"] + (["error personalised (mm)", "error generic (mm)"] if truth else [])
    items = ["gait2392 scaled to this subject's static markers as OpenSim's ScaleTool does (uniform per body, "
             "bony-landmark marker pairs; factors " + ", ".join(f"{b} {f:.3f}" for b, f in generic["scale_factors"].items())
             + "), its markers placed on the static pose and every trial tracked by the same IK "
             f"({generic['model']}). " + " ".join(generic.get("notes", [])),
             Table(head, crow, caption="Joint centres of the two models in the static pose (model ground)"
                                       + ("; errors against the phantom truth" if truth else ""))]
    trow = [[t, round(v["marker_rms_mm"]["personalised"], 2), round(v["marker_rms_mm"]["generic"], 2),
             ", ".join(f"{c} {d:.1f}" for c, d in v["angle_rms_difference_deg"].items())]
            for t, v in generic["trials"].items()]
    if trow:
        items.append(Table(["trial", "marker RMS personalised (mm)", "marker RMS generic (mm)",
                            "RMS angle difference (deg)"], trow, caption="The same IK on both models"))
    if truth.get("angle_rmse_deg"):
        items.append(Table(["angle", "RMSE personalised (deg)", "RMSE generic (deg)"],
                           [[c, round(v["personalised"], 2), round(v["generic"], 2)]
                            for c, v in truth["angle_rmse_deg"].items()], caption="Gait angles against the truth"))
    name = next((k for k in generic["trials"] if k.startswith("gait")), next(iter(generic["trials"]), None))
    mot = folder / "generic" / f"{name}.mot" if name else None
    if mot is not None and mot.is_file() and name in ik:
        tab, res = read_mot(mot), ik[name]
        fig = new_figure(12, 3.2)
        for ax, jn in zip(fig.subplots(1, 3), ("hip_flexion", "knee_flexion", "ankle_angle")):
            for s in sides:
                c, colour = f"{jn}_{s}", SIDE_COLOURS.get(s.upper())
                if c in res.coordinates:
                    ax.plot(res.time, np.degrees(res.q[:, res.coordinates.index(c)]), color=colour, label=f"{s} personalised")
                g = c.replace("knee_flexion", "knee_angle")
                if g in tab.columns:
                    v = tab.values[:, tab.columns.index(g)] * (-1.0 if jn == "knee_flexion" else 1.0)
                    ax.plot(tab.time, v if tab.in_degrees else np.degrees(v), color=colour, ls="--",
                            label=f"{s} scaled gait2392")
            ax.set_title(jn)
            ax.set_xlabel("time (s)")
            ax.set_ylabel("deg")
            ax.legend(fontsize=7)
        fig.tight_layout()
        items.append(Figure(fig, caption=f"{name}: sagittal angles, personalised (solid) and scaled gait2392 (dashed)"))
    return Section("Against gait2392 scaled to the same markers", items)


def _patella_section(tracks: dict):
    """The patellofemoral joint: patellar flexion against knee flexion and the patella's sagittal path, per side."""
    from .gait_plots import SIDE_COLOURS
    from .html_report import Figure, Section, new_figure

    fig = new_figure(10, 3.6)
    a1, a2 = fig.subplots(1, 2)
    for s, t in tracks.items():
        colour = SIDE_COLOURS.get(s.upper())
        a1.plot(t["flexion_deg"], t["patellar_flexion_deg"], color=colour,
                label=f"{s}: {t['patellar_flexion_per_knee_flexion']:.2f} deg/deg")
        xy = np.asarray(t["centre_path_mm"], float)
        a2.plot(xy[:, 0], xy[:, 1], color=colour, marker=".", label=s)
    q = np.array([0.0, 120.0])
    first = next(iter(tracks.values()))
    y0 = float(np.interp(0.0, first["flexion_deg"], first["patellar_flexion_deg"]))
    a1.fill_between(q, y0 + 0.6 * q, y0 + 0.7 * q, color="0.85", label="in vivo slope: 30-40 % lag")
    a1.set_xlabel("knee flexion (deg)")
    a1.set_ylabel("patellar flexion (deg)")
    a1.legend(fontsize=7)
    a2.set_xlabel("anterior (mm, knee frame)")
    a2.set_ylabel("proximal (mm)")
    a2.set_aspect("equal")
    a2.legend(fontsize=7)
    fig.tight_layout()
    return Section("Patellofemoral joint", [
        "The patella moves on the subject's femur as a planar three-force member (Yamaguchi & Zajac 1989): the "
        "patellar tendon keeps its MRI length, the articular surface its MRI clearance, and quadriceps, tendon and "
        "contact forces balance. Converged over knee flexion "
        + ", ".join(f"{s} {t['flexion_deg'][0]:.0f} to {t['flexion_deg'][-1]:.0f} deg (tendon {t['tendon_length_mm']:.1f} mm)"
                    for s, t in tracks.items())
        + "; linear beyond. In the model: joint patellofemoral_<s>, coordinate knee_flexion_<s>_beta coupled to knee "
          f"flexion ({first['frame']}).",
        Figure(fig, caption="Patellar flexion against knee flexion (grey: the in-vivo range) and the patella "
                            "centre's path in the femur's knee frame")])
