"""Benchmark: the correlative-knee experiments of Pronost et al. (2010), section 4.1, on motion phantoms.

Two IK protocols, each run through the whole experiment (training, Tables 3-5):

* ``seed7`` (the seed's, section 3.2: "an IK solver driven by the positions of
  the seven markers", equal weights): one-leg model (pelvis, right thigh and
  shank; pelvis rotations locked, so pelvis translation + hip rotations are the
  thigh's free six DOF; left leg and right foot removed: no tracked marker sees
  them), IK on the seven seed-marker analogues only, right knee learnt and
  compared, scored on the same seven markers;
* ``whole-body``: every skin marker of the pelvis and both legs tracked, both
  knees learnt and compared, scored on the seven seed-marker analogues and on
  all nine right thigh and shank markers.

Experiment (the seed's, on phantoms with soft-tissue artefact and 0.5 mm noise):

* subject 1 = phantom seed A, subject 2 = phantom seed B (another anatomy and
  stature, its own knee law and artefact);
* training per subject: 5 gait cycles and one crouch at each foot angle
  (0, 30, 60, 90, 120, 180 deg); test (subject 1 only): 10 other gait cycles
  and 10 other crouches (foot angles in turn), 100 Hz;
* on the training trials a free six-DOF knee is tracked by IK (the protocol's
  markers, equal weights; the bone-fixed TIBM1/TIBM2 device markers are never
  used); from its frames, per motion: the correlative law (3+DOF), the planar
  spline knee (3DOF, natural cubic splines of flexion, gait2392 style) and the
  hinge (1DOF: the planar knee's axis and its centre at zero flexion, as the
  seed; ``1DOF-LS``, the least-squares constant knee, is reported as well);
* Table 3: IK of the test trials with each knee (motion-specific models); for
  the crouch both the global law (all foot angles) and the sub-motion laws of
  seed 3.3 (every knee model fitted on the training crouch of one foot angle,
  each test crouch tracked with the models of its own foot angle), plus the
  reductions per foot angle and the free six-DOF knee's (the STA floor);
  Table 4: subject 1's law vs subject 2's law scaled by eq. (3) (RGT-RLFE and
  RMFE-RLFE distances: phantom landmarks RTRO, RKNE, RMFC); Table 5: gait law
  on crouch trials and crouch law on gait trials.
* Score (seed): sum over frames of the frame RMS distance between measured and
  model markers (m, not normalised), averaged over the 10 trials; scored on the
  analogues of the seed's seven right-leg markers (RGT -> RTHIP, RLFE -> RKNE,
  RMFE -> RKNEM, RTT -> RTIBM3, RFH -> RTIB, RLATMAL -> RANK, RMEDMAL -> RANKM);
  also reported on all nine right thigh and shank markers (whole-body protocol).
* Knee kinematics vs truth: RMS error of the right knee's six coordinates of the
  test IK against the phantom's true coordinates (a better marker fit is not a
  truer knee: the free and correlative knees absorb part of the thigh STA).

Usage::

    python benchmarks/correlative.py [--quick] [--protocol seed7 whole-body] [--seed-a 0] [--seed-b 1]
                                     [--json benchmarks/results/correlative.json]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lowerlimb.atomic import write_text  # noqa: E402
from kinematics.mechanisms.law_transfer import scale_factor  # noqa: E402
from lowerlimb.json_format import json_text  # noqa: E402
from personalize.presentation.correlative_tables import TextTable, coefficient_table  # noqa: E402
from correlative_experiments import (  # noqa: E402
    SEED_MARKERS, CorrelativeKnee, FreeKnee, compare_knees, knee_coordinate_errors, compare_knees_by_sub_motion, reduction, score_results,
    seed_protocol, sub_motion_knees, summarize, tracking_table, train_knees, whole_body_protocol,
)

LEG_MARKERS = tuple(f"R{m}" for m in ("THI", "THIP", "THIA", "KNE", "KNEM", "TIB", "TIBM3", "ANK", "ANKM"))
#: seed section 4.1 reductions, percent (mean, sd)
SEED_REDUCTIONS = {"gait": {"vs_1DOF": (44, 8), "vs_3DOF": (31, 5)}, "crouch": {"vs_1DOF": (71, 9), "vs_3DOF": (66, 6)}}
ANGLES = (0, 30, 60, 90, 120, 180)


def foot_angle(label: str) -> str:
    """Sub-motion key of a crouch trial label ``crouch_AAA_NN[.c3d]``: the foot angle ``AAA``."""
    return label.split("_")[1]


def subject_trials(seed: int, stature: float, n_gait: int, n_crouch_repeats: int, rate: float, progress,
                   sta_scale: float = 1.0):
    from phantoms import make_phantom
    from phantoms.motion import make_trials

    ph = make_phantom(seed, stature=stature)
    sk, trials, _ = make_trials(ph, seed, rate=rate, gait_trials=n_gait, gait_cycles=1.0, crouch_angles=ANGLES,
                                crouch_repeats=n_crouch_repeats, crouch_duration=3.0, functional_ranges=(),
                                sta_scale=sta_scale)
    progress(f"phantom seed {seed}: {len(trials)} trials")
    bt = ph.body_truth()["bones"]
    landmarks = {s: {n: np.asarray(bt[f"femur_{s}"]["landmarks"][f"{s.upper()}{n}"], float) for n in ("TRO", "KNE", "MFC")}
                 for s in ("r", "l")}
    return sk, {t.name: t for t in trials}, landmarks


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed-a", type=int, default=0)
    ap.add_argument("--seed-b", type=int, default=1)
    ap.add_argument("--stature-b", type=float, default=1.62, help="stature of subject 2 (m)")
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--train-gait", type=int, default=5)
    ap.add_argument("--test", type=int, default=10, help="test gait and crouch trials each")
    ap.add_argument("--sta-scale", type=float, default=1.0, help="soft-tissue artefact amplitude factor (1 = phantom default)")
    ap.add_argument("--protocol", nargs="+", choices=("seed7", "whole-body"), default=["seed7", "whole-body"],
                    help="IK protocols to run (seed7: seven markers of one leg, one-leg model; whole-body: all skin markers)")
    ap.add_argument("--quick", action="store_true", help="3 test trials, 50 Hz (smoke run)")
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "correlative.json")
    args = ap.parse_args(argv)
    if args.quick:
        args.test, args.rate, args.train_gait = 3, 50.0, 3

    from rich.console import Console

    con = Console(stderr=True)
    log = lambda msg: con.log(msg)  # noqa: E731
    t_start = time.perf_counter()
    n_rep = 1 + int(np.ceil(args.test / len(ANGLES)))
    skA, trA, lmA = subject_trials(args.seed_a, 1.75, args.train_gait + args.test, n_rep, args.rate, log,
                                  args.sta_scale)
    skB, trB, lmB = subject_trials(args.seed_b, args.stature_b, args.train_gait, 1, args.rate, log, args.sta_scale)
    skin = [n for n in next(iter(trA.values())).markers.names if not n.endswith(("TIBM1", "TIBM2"))]
    seven = tuple(SEED_MARKERS.values())
    protocols = {"seed7": (seed_protocol(seven, "r"), {"seed7": seven}),
                 "whole-body": (whole_body_protocol(skin), {"seed7": seven, "leg9": LEG_MARKERS})}

    def split(tr, n_train_gait, n_test):
        train = {"gait": [tr[f"gait_{i + 1:02d}"].markers for i in range(n_train_gait)],
                 "crouch": [tr[f"crouch_{a:03d}_01"].markers for a in ANGLES]}
        test = {"gait": [tr[f"gait_{n_train_gait + i + 1:02d}"].markers for i in range(n_test)] if n_test else [],
                "crouch": [tr[f"crouch_{ANGLES[i % len(ANGLES)]:03d}_{2 + i // len(ANGLES):02d}"].markers
                           for i in range(n_test)]}
        return train, test

    trainA, testA = split(trA, args.train_gait, args.test)
    # true coordinates of the test trials' frames (same order as testA), for the knee kinematics errors
    by_source = {t.markers.source: t.q for t in trA.values()}
    truthA = {m: [by_source[t.source] for t in testA[m]] for m in testA}
    true_names = skA.model.coordinate_names
    trainB, _ = split(trB, args.train_gait, 0)
    s_scale = {s: scale_factor(lmA[s], lmB[s], "TRO", "KNE", "MFC") for s in ("r", "l")}
    report = {"benchmark": "correlative", "seed": "Pronost, Sandholm & Thalmann 2010, section 4.1, Tables 3-5",
              "units": "sum_rms_m: sum over frames of the frame RMS marker distance (m); mean_rms_m: mean frame RMS (m)",
              "protocol": {"subject1_phantom_seed": args.seed_a, "subject2_phantom_seed": args.seed_b,
                           "subject2_stature_m": args.stature_b, "rate_hz": args.rate,
                           "training": {"gait": args.train_gait, "crouch": len(ANGLES)},
                           "test": {"gait": args.test, "crouch": args.test},
                           "seed_marker_analogues": SEED_MARKERS, "noise_sd_m": 0.0005,
                           "soft_tissue_artefact_scale": args.sta_scale, "eq3_scale_factor": s_scale},
              "protocols": {}}
    tables_md = []
    headline = []
    for pname in args.protocol:
        proto, scored = protocols[pname]
        sides = proto.sides
        mA, mB = proto.model(skA.model), proto.model(skB.model)
        log(f"[bold]protocol {pname}[/bold]: IK model {mA.name} ({mA.n_q} coordinates), {len(proto.tracked)} markers tracked")
        # ---- training: free six-DOF knee IK, then every knee model (per subject and motion)
        knees = {}
        for subj, m, train in (("A", mA, trainA), ("B", mB, trainB)):
            for motion in ("gait", "crouch"):
                t = time.perf_counter()
                knees[subj, motion] = train_knees(m, train[motion], proto.tracked, sides)
                log(f"  subject {subj} {motion}: free-knee IK on {len(train[motion])} trials, "
                    f"marker RMS {1e3 * knees[subj, motion].training_rms:.2f} mm ({time.perf_counter() - t:.1f} s)")
        # seed 3.3: crouch models per sub-motion (foot angle), each fitted on its own training crouch(es)
        sub_knees = sub_motion_knees(knees["A", "crouch"], foot_angle)
        from2 = {motion: tuple(CorrelativeKnee(s, knees["B", motion].laws[s].scaled(s_scale[s]), "3+DOF from2")
                               for s in sides) for motion in ("gait", "crouch")}

        # ---- IK of the test trials with every knee model
        results = {}
        for motion in ("gait", "crouch"):
            other = "crouch" if motion == "gait" else "gait"
            sets = dict(knees["A", motion].models)
            sets["3+DOF from2"] = from2[motion]
            sets[f"3+DOF {other} law"] = knees["A", other].models["3+DOF"]
            sets["6DOF"] = tuple(FreeKnee(s) for s in sides)                 # floor: no knee model can do better
            sets["true knee"] = tuple(CorrelativeKnee(s, skA.knee_laws[s], "true knee") for s in sides)
            t = time.perf_counter()
            results[motion] = compare_knees(mA, sets, testA[motion], proto.tracked)
            if motion == "crouch":
                results[motion].update(compare_knees_by_sub_motion(mA, sub_knees, testA[motion], foot_angle,
                                                                   proto.tracked))
            log(f"  {motion}: {len(sets)} knee models (+ sub-motion models for crouch) x {len(testA[motion])} test "
                f"trials ({time.perf_counter() - t:.1f} s)")

        section = {"ik_model": mA.name, "tracked_markers": list(proto.tracked), "knees": list(sides),
                   "locked_coordinates": [c.name for c in mA.coordinates if c.locked],
                   "coordinates": list(mA.coordinate_names),
                   "training_marker_rms_m": {f"{s} {m}": knees[s, m].training_rms for s, m in knees},
                   "scored_markers": {k: list(v) for k, v in scored.items()}, "scoring": {}}
        tables_md.append(f"## Protocol {pname}: IK on {len(proto.tracked)} markers, model {mA.name}\n")
        for sname, markers in scored.items():
            sec, md, head = score_tables(pname, sname, results, testA, markers)
            section["scoring"][sname] = sec
            tables_md += md
            headline.append(head)
        kin_table, kin_json = knee_error_table(pname, results, truthA, true_names)
        section["knee_coordinate_rms_error_vs_truth"] = kin_json
        tables_md.append(kin_table.to_markdown())
        laws = {f"subject1 {m}": knees["A", m].laws["r"] for m in ("gait", "crouch")}
        laws.update({f"subject2 {m} scaled": from2[m][0].law for m in ("gait", "crouch")})
        laws["phantom truth"] = skA.knee_laws["r"]
        tables_md.append(f"Right knee laws ({pname} protocol):\n" + coefficient_table(laws, digits=4, with_sd=False).to_markdown())
        section["laws_right_knee"] = {k: v.to_json() for k, v in laws.items()}
        report["protocols"][pname] = section
    report["seconds"] = time.perf_counter() - t_start
    summary = TextTable(("protocol", "scored", "gait vs 1DOF", "gait vs 3DOF", "crouch vs 1DOF", "crouch vs 3DOF",
                         "crouch sub vs 1DOF", "crouch sub vs 3DOF", "6DOF floor crouch vs 1DOF/3DOF"),
                        tuple(headline) + (("seed (Pronost 2010)", "7 markers", "44 (8)", "31 (5)", "71 (9)", "66 (6)",
                                            "", "", ""),),
                        "Reductions of the IK error by the correlative 3+DOF knee, % mean (sd) over test trials")
    tables_md.append(summary.to_markdown())
    text = "\n".join(tables_md)
    print(text)
    report["tables_markdown"] = text
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_text(args.json, json_text(report) + "\n")
    print(f"wrote {args.json} ({report['seconds']:.0f} s)")
    return 0


def knee_error_table(pname, results, truth, true_names):
    """Right-knee coordinate errors of the test IK vs the phantom's true coordinates, per knee model and motion."""
    labels = ("1DOF", "3DOF", "3+DOF", "3+DOF from2", "6DOF", "true knee")
    rows, out = [], {}
    for motion in ("gait", "crouch"):
        for lab in labels:
            e = np.mean([knee_coordinate_errors(r, qt, true_names, "r") for r, qt in zip(results[motion][lab], truth[motion])],
                        axis=0)
            out[f"{motion} {lab}"] = {"rotations_rad": e[:3].tolist(), "translations_m": e[3:].tolist()}
            rows.append((motion, lab) + tuple(f"{np.degrees(v):.2f}" for v in e[:3]) + tuple(f"{1e3 * v:.2f}" for v in e[3:]))
    return TextTable(("motion", "knee model", "flexion deg", "adduction deg", "rotation deg", "tx mm", "ty mm", "tz mm"),
                     tuple(rows), f"Right knee coordinates of the test IK vs the phantom's truth ({pname} protocol): "
                                  "RMS error over frames, mean over test trials"), out


def score_tables(pname, sname, results, testA, markers):
    """Tables 3, 4, 5, the reductions (global, sub-motion, per foot angle) of one protocol on one scored marker set."""
    sc = {m: score_results(results[m], testA[m], markers) for m in ("gait", "crouch")}
    tag = f"{pname} protocol, {sname} markers"
    sub_row = {lab: sc["crouch"][f"{lab} sub"] for lab in ("1DOF", "3DOF", "3+DOF")}
    t3 = tracking_table({"Gait": sc["gait"], "Crouch (global law)": sc["crouch"], "Crouch (sub-motion laws)": sub_row},
                        ("1DOF", "3DOF", "3+DOF", "1DOF-LS", "6DOF"),
                        f"Table 3 ({tag}): average sum of frame RMS distances (m) (mean frame RMS)")
    t4 = tracking_table({"Gait": {"model1": sc["gait"]["3+DOF"], "model1from2": sc["gait"]["3+DOF from2"]},
                         "Crouch": {"model1": sc["crouch"]["3+DOF"], "model1from2": sc["crouch"]["3+DOF from2"]}},
                        ("model1", "model1from2"),
                        f"Table 4 ({tag}): tracking errors (m) of model1 and model1from2")
    t5 = tracking_table({"Gait": {"3+DOF gait": sc["gait"]["3+DOF"], "3+DOF crouch": sc["gait"]["3+DOF crouch law"]},
                         "Crouch": {"3+DOF gait": sc["crouch"]["3+DOF gait law"], "3+DOF crouch": sc["crouch"]["3+DOF"]}},
                        ("3+DOF gait", "3+DOF crouch"),
                        f"Table 5 ({tag}): tracking errors (m) of motion-specific models")
    red = {m: {"vs_1DOF": reduction(sc[m]["3+DOF"], sc[m]["1DOF"]), "vs_3DOF": reduction(sc[m]["3+DOF"], sc[m]["3DOF"]),
               "vs_1DOF-LS": reduction(sc[m]["3+DOF"], sc[m]["1DOF-LS"]),
               "3DOF_vs_1DOF": reduction(sc[m]["3DOF"], sc[m]["1DOF"]),
               "6DOF_floor_vs_1DOF": reduction(sc[m]["6DOF"], sc[m]["1DOF"]),
               "6DOF_floor_vs_3DOF": reduction(sc[m]["6DOF"], sc[m]["3DOF"])} for m in ("gait", "crouch")}
    red["crouch sub-motion"] = {"vs_1DOF": reduction(sc["crouch"]["3+DOF sub"], sc["crouch"]["1DOF sub"]),
                                "vs_3DOF": reduction(sc["crouch"]["3+DOF sub"], sc["crouch"]["3DOF sub"]),
                                "vs_global_1DOF": reduction(sc["crouch"]["3+DOF sub"], sc["crouch"]["1DOF"]),
                                "vs_global_3DOF": reduction(sc["crouch"]["3+DOF sub"], sc["crouch"]["3DOF"]),
                                "vs_global_3+DOF": reduction(sc["crouch"]["3+DOF sub"], sc["crouch"]["3+DOF"])}
    pairs = (("3+DOF", "1DOF"), ("3+DOF", "3DOF"), ("3+DOF sub", "1DOF sub"), ("3+DOF sub", "3DOF sub"),
             ("6DOF", "1DOF"), ("6DOF", "3DOF"))
    per_angle, rows = {}, []
    for a in ANGLES:
        idx = [i for i, t in enumerate(testA["crouch"]) if foot_angle(t.source) == f"{a:03d}"]
        if not idx:
            continue
        pick = lambda lab: [sc["crouch"][lab][i] for i in idx]  # noqa: E731
        per_angle[a] = {f"{b} vs {w}": reduction(pick(b), pick(w))[0] for b, w in pairs}
        rows.append((f"{a} deg ({len(idx)})",) + tuple(f"{per_angle[a][f'{b} vs {w}']:.0f}" for b, w in pairs))
    red["crouch per foot angle (mean over its test trials)"] = per_angle
    t_angle = TextTable(("foot angle (trials)",) + tuple(f"{b} vs {w}" for b, w in pairs), tuple(rows),
                        f"Crouch reductions per foot angle ({tag}), % (mean over the angle's test trials)")
    t_red = TextTable(("motion", "3+DOF vs 1DOF", "3+DOF vs 3DOF", "3+DOF vs 1DOF-LS", "3DOF vs 1DOF",
                       "6DOF floor vs 1DOF", "6DOF floor vs 3DOF", "seed 3+DOF vs 1DOF / 3DOF"),
                      tuple((m,) + tuple(f"{red[m][k][0]:.0f} ({red[m][k][1]:.0f})" for k in
                                         ("vs_1DOF", "vs_3DOF", "vs_1DOF-LS", "3DOF_vs_1DOF", "6DOF_floor_vs_1DOF",
                                          "6DOF_floor_vs_3DOF"))
                            + (f"{SEED_REDUCTIONS[m]['vs_1DOF'][0]} / {SEED_REDUCTIONS[m]['vs_3DOF'][0]}",)
                            for m in ("gait", "crouch"))
                      + (("crouch sub-motion",) + tuple(f"{red['crouch sub-motion'][k][0]:.0f} ({red['crouch sub-motion'][k][1]:.0f})"
                                                        for k in ("vs_1DOF", "vs_3DOF")) + ("", "", "", "", "71 / 66"),),
                      f"Reductions of the tracking error ({tag}), % mean (sd) over test trials")
    order = {m: bool(summarize(sc[m]["3+DOF"])["sum_rms_m_mean"] < summarize(sc[m]["3DOF"])["sum_rms_m_mean"]
                     < summarize(sc[m]["1DOF"])["sum_rms_m_mean"]) for m in ("gait", "crouch")}
    truth = (f"True phantom knee (law known, {tag}): gait {1e3 * summarize(sc['gait']['true knee'])['mean_rms_m']:.2f} mm, "
             f"crouch {1e3 * summarize(sc['crouch']['true knee'])['mean_rms_m']:.2f} mm mean frame RMS; free 6DOF knee "
             f"gait {1e3 * summarize(sc['gait']['6DOF'])['mean_rms_m']:.2f} mm, "
             f"crouch {1e3 * summarize(sc['crouch']['6DOF'])['mean_rms_m']:.2f} mm.\n")
    section = {
        "summary": {m: {lab: summarize(v) for lab, v in sc[m].items()} for m in ("gait", "crouch")},
        "per_trial": {m: {lab: [s.to_dict() for s in v] for lab, v in sc[m].items()} for m in ("gait", "crouch")},
        "reductions_percent_mean_sd": red, "seed_reductions_percent": SEED_REDUCTIONS,
        "meets_seed_reductions": {m: {k: bool(red[m][k][0] >= SEED_REDUCTIONS[m.split()[0]][k][0]) for k in ("vs_1DOF", "vs_3DOF")}
                                  for m in ("gait", "crouch", "crouch sub-motion")},
        "ordering_correlative_lt_3dof_lt_1dof": order,
        "tables_markdown": [t.to_markdown() for t in (t3, t4, t5, t_red, t_angle)],
    }
    f = lambda r: f"{r[0]:.0f} ({r[1]:.0f})"  # noqa: E731
    head = (pname, sname, f(red["gait"]["vs_1DOF"]), f(red["gait"]["vs_3DOF"]), f(red["crouch"]["vs_1DOF"]),
            f(red["crouch"]["vs_3DOF"]), f(red["crouch sub-motion"]["vs_1DOF"]), f(red["crouch sub-motion"]["vs_3DOF"]),
            f"{red['crouch']['6DOF_floor_vs_1DOF'][0]:.0f} / {red['crouch']['6DOF_floor_vs_3DOF'][0]:.0f}")
    return section, [t.to_markdown() for t in (t3, t4, t5, t_red, t_angle)] + [truth], head


if __name__ == "__main__":
    raise SystemExit(main())
