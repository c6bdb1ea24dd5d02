"""Benchmark: gait events, Plug-in-Gait kinetics against Nexus, gait-cycle reports, and the foot element on real stances.

On ../shared/data/mocap_pig/Movement_trial.c3d (a stair descent over four
force plates, 120 Hz, Nexus' own Plug-in-Gait outputs stored):

1. plates: number, CoP inside its plate while loaded, foot on each;
2. gait events from the plates (20 N threshold) and from kinematics (Zeni et
   al. 2008), frame by frame; the C3D's own EVENT group;
3. Plug-in-Gait moments and powers against Nexus' stored values: mean
   |ours - Nexus| over the plate stances as % of Nexus' range;
4. angles, moments and powers per % gait cycle (CSV + gait-lab plots);
5. the foot-ground contact element identified on each plate stance (eq. 25):
   parameters, RMS angle and height errors, a Fig.-9-like plot.

And on ../shared/data/opensim_gait2392/subject01_walk1 (treadmill walk, 60 Hz):
Zeni events against the ground-reaction .mot (20 N).

Usage::

    python benchmarks/gait_kinetics.py --out /tmp/gait [--json /tmp/gait/gait_kinetics.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DATA = REPO.parent / "shared" / "data"


def _events_table(ev):
    return [{"side": e.side, "kind": e.kind, "frame": e.frame, "time_s": round(e.time, 4), "source": e.source} for e in ev]


def _match(ref, other, kind, side):
    """Signed time differences (s) of `other` events to the nearest `ref` event of the same kind and side."""
    a = [e for e in ref if e.kind == kind and e.side == side]
    b = [e for e in other if e.kind == kind and e.side == side]
    out = []
    for e in a:
        if b:
            n = min(b, key=lambda x: abs(x.time - e.time))
            if abs(n.time - e.time) < 0.3:
                out.append({"ref_frame": e.frame, "frame": n.frame, "diff_s": round(n.time - e.time, 4)})
    return out


def mocap_pig(data: Path, out: Path) -> dict:
    from kinematics.io.c3d import read_c3d, read_c3d_outputs
    from lowerlimb.errors import FitError, InputError
    from kinematics.gait.foot_contact import (
        FootElement,
        FootParameters,
        fit_foot_parameters,
        sagittal_stance,
    )
    from kinematics.gait.plate_contacts import assign_feet
    from kinematics.io.forceplates import read_force_plates
    from kinematics.gait.gait_cycles import (
        c3d_events,
        cycle_statistics,
        events_from_kinematics,
        events_from_plates,
        gait_cycles,
        write_cycles_csv,
    )
    from kinematics.gait.pig import plug_in_gait, static_foot_offsets
    from kinematics.gait.pig_kinetics import ground_reactions, plug_in_gait_kinetics
    from kinematics.gait.subject import read_vsk
    from personalize.presentation.gait_plots import (
        plot_foot_angle_fit,
        plot_gait_grid,
        plot_power_row,
    )

    path = data / "Movement_trial.c3d"
    sub = static_foot_offsets(read_c3d(data / "Static_trial.c3d"), read_vsk(data / "Test.vsk"))
    trial = read_c3d(path)
    nexus = read_c3d_outputs(path)
    plates = read_force_plates(path)
    contacts = assign_feet(plates, trial)
    res = {"plates": {"n": len(plates), "cop_outside_loaded_frames": int(sum(p.cop_outside[p.loaded].sum() for p in plates)),
                      "contacts": [c.describe() for c in contacts]}}
    ev_p = events_from_plates(plates, contacts)
    ev_k = events_from_kinematics(trial)
    res["events"] = {"plates": _events_table(ev_p), "kinematics": _events_table(ev_k),
                     "c3d_EVENT_group": _events_table(c3d_events(path)),
                     "kinematics_vs_plates": {f"{s}_{k}": _match(ev_p, ev_k, k, s) for s in "RL" for k in ("strike", "off")}}
    pig = plug_in_gait(trial, sub)
    grf, notes = ground_reactions(plates, contacts, trial.n_frames)
    t0 = time.perf_counter()
    kin = plug_in_gait_kinetics(trial, pig, sub.mass, grf)
    res["kinetics_s"] = round(time.perf_counter() - t0, 4)
    res["kinetics_notes"] = list(notes) + list(kin.notes)
    cmp = {}
    for s, sfx in (("R", "_r"), ("L", "_l")):
        ng = nexus[s + "GroundReactionForce"]
        st = grf[s].loaded & np.all(np.isfinite(ng), 1) & (np.abs(ng[:, 2]) > 0)
        for joint, name in (("hip", "Hip"), ("knee", "Knee"), ("ankle", "Ankle")):
            a = kin.moment_per_kg(joint + sfx, "N mm/kg")[st]
            b = nexus[f"{s}{name}Moment"][st] * 1e3
            e = np.nanmean(np.abs(a - b), 0) / (np.nanmax(b, 0) - np.nanmin(b, 0)) * 100
            p, q = kin.power_per_kg(joint + sfx)[st], nexus[f"{s}{name}Power"][st, 2]
            cmp[joint + sfx] = {"moment_err_pct_of_range_xyz": [round(float(v), 2) for v in e],
                                "power_err_pct_of_range": round(float(np.nanmean(np.abs(p - q)) / (np.nanmax(q) - np.nanmin(q)) * 100), 2),
                                "stance_frames": [int(np.flatnonzero(st)[0]), int(np.flatnonzero(st)[-1])]}
    res["pig_kinetics_vs_nexus"] = cmp

    # gait cycles from the plate events
    stats, units = {}, {"angle": "deg", "moment": "N mm/kg", "power": "W/kg"}
    cyc = {s: gait_cycles(ev_p, s) for s in "RL"}
    res["cycles"] = {s: [(c.start.frame, c.off.frame if c.off else None, c.end.frame) for c in cyc[s]] for s in "RL"}
    for s, sfx in (("R", "_r"), ("L", "_l")):
        if not cyc[s]:
            continue
        for joint in ("hip", "knee", "ankle"):
            stats[(f"{joint}_angle", s)] = cycle_statistics(np.degrees(pig.angles[joint + sfx]), trial.time, cyc[s])
            stats[(f"{joint}_moment", s)] = cycle_statistics(kin.moment_per_kg(joint + sfx, "N mm/kg"), trial.time, cyc[s])
            stats[(f"{joint}_power", s)] = cycle_statistics(kin.power_per_kg(joint + sfx), trial.time, cyc[s])
    out.mkdir(parents=True, exist_ok=True)
    write_cycles_csv(out / "gait_cycles.csv", stats, {f"{k}s": v for k, v in units.items()},
                     note="Movement_trial.c3d, Plug-in-Gait, events from the force plates")
    plot_gait_grid(out / "angles.png", stats, "angle", "deg", title="Movement_trial: joint angles (Plug-in-Gait)")
    plot_gait_grid(out / "moments.png", stats, "moment", "N mm/kg", title="Movement_trial: joint moments (Plug-in-Gait, internal)")
    plot_power_row(out / "powers.png", stats)

    # foot element on each usable plate stance
    static = read_c3d(data / "Static_trial.c3d")
    spig = plug_in_gait(static, sub)
    up = np.array([0.0, 0.0, 1.0])
    phases, fits = [], []
    element = FootElement()
    for c in contacts:
        if not c.usable or "partial" in c.flags:
            continue
        s, sfx = c.foot, "_" + c.foot.lower()
        fr = np.arange(c.start, c.stop)
        p = plates[c.plate]
        loaded = fr[p.force[fr] @ up > 0.2 * sub.mass * 9.81]
        axis_static = -np.nanmean(spig.segments["foot" + sfx].axes[:, :, 2], axis=0)
        neutral = np.arctan2(axis_static @ up, np.linalg.norm(axis_static - (axis_static @ up) * up))
        axis = -pig.segments["foot" + sfx].axes[loaded, :, 2]
        st = sagittal_stance(pig.centres["ankle" + sfx][loaded], axis, p.force[loaded], p.cop[loaded], up)
        ang = st["angle"] - neutral
        ground = st["ground"]
        h0 = float(np.median(st["ankle"][:, 1] - ground))
        x0 = FootParameters(300.0, 0.05, 0.08, 0.06, h0)
        try:
            fit = fit_foot_parameters(element, st["ankle"], ang, st["force"], st["moment"], ground, x0)
        except (FitError, InputError) as err:  # a stance the element cannot balance is reported, not hidden
            fits.append({"contact": c.describe(), "error": str(err)})
            continue
        fits.append({"contact": c.describe(), "frames": [int(loaded[0]), int(loaded[-1])],
                     "parameters": dict(zip(FootParameters.NAMES, [round(float(v), 4) for v in fit.parameters.as_vector()])),
                     "sd": [round(float(v), 4) for v in fit.sd],
                     "rms_angle_deg": round(float(np.degrees(fit.rms_angle)), 3),
                     "rms_height_mm": round(fit.rms_height * 1e3, 2),
                     "measured_angle_range_deg": [round(float(np.degrees(ang.min())), 2), round(float(np.degrees(ang.max())), 2)],
                     "balanced_frames": int(fit.equilibrium.converged.sum()), "frames_used": len(loaded)})
        pct = 100.0 * (loaded - c.start) / max(c.stop - 1 - c.start, 1)
        phases.append({"label": f"{s} foot, plate {c.plate + 1}", "percent": pct, "measured": np.degrees(ang),
                       "simulated": np.degrees(fit.equilibrium.angle)})
    res["foot_element"] = fits
    if phases:
        plot_foot_angle_fit(out / "foot_element_fig9.png", phases)
    return res


def subject01_walk(data: Path) -> dict:
    from kinematics.gait.gait_cycles import (
        events_from_kinematics,
        events_from_vertical_force,
    )
    from kinematics.io.storage import read_mot, read_trc

    trial = read_trc(data / "subject01_walk1.trc")
    grf = read_mot(data / "subject01_walk1_grf.mot")
    cols = list(grf.columns)
    ref = []
    for side, prefix in (("R", ""), ("L", "1_")):  # ExternalForce_1 -> calcn_r, _2 -> calcn_l
        ref += events_from_vertical_force(grf.time, grf.values[:, cols.index(prefix + "ground_force_vy")], side,
                                          source="grf.mot")
    ev = events_from_kinematics(trial, heel="{s}.Heel", toe="{s}.Toe.Tip", sacrum="V.Sacral", up=(0, 1, 0))
    return {"grf": _events_table(ref), "kinematics": _events_table(ev),
            "kinematics_vs_grf": {f"{s}_{k}": _match(ref, ev, k, s) for s in "RL" for k in ("strike", "off")}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    result = {"units": "moments N mm/kg, powers W/kg, angles deg, errors % of Nexus' range over the plate stances"}
    if (args.data / "mocap_pig").is_dir():
        result["mocap_pig"] = mocap_pig(args.data / "mocap_pig", args.out)
    if (args.data / "opensim_gait2392").is_dir():
        result["subject01_walk1"] = subject01_walk(args.data / "opensim_gait2392")
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        from lowerlimb.atomic import write_text

        write_text(args.json, text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
