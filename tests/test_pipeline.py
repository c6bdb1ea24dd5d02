"""`personalize.pipeline.run_subject` and ``personalize run`` on a small phantom subject."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from lowerlimb.errors import InputError
from personalize.cli import main
from personalize.evaluation.phantom_subject import write_phantom_subject
from personalize.pipeline import find_inputs, run_subject

#: phantom seed of the module's subject (see `subject`)
SEED = 5


@pytest.fixture(scope="module")
def subject(tmp_path_factory):
    """A phantom subject folder with short trials (2 mm labels) and its pipeline output.

    Seed 5: pelvis soft tissue near the population median (ASIS 6.9 mm, PSIS 19.5 mm; `kinematics.gait.soft_tissue`).
    The tail of that distribution (seed 2 draws a 54 mm ASIS, +3 sd, and its MRI hip is 3 cm off, unobservable
    from the markers) is the validation runs' business, not this test's.
    """
    root = tmp_path_factory.mktemp("pipeline")
    subj = write_phantom_subject(root / "subject", seed=SEED, voxel_mm=2.0)
    out = root / "out"
    summary = run_subject(subj, out)
    return subj, out, summary


def test_outputs_written(subject):
    subj, out, summary = subject
    for f in ("model.osim", "model.json", "summary.json", "report.html", "landmarks.json", "joints.json",
              "meshes/femur_r.stl", "meshes/pelvis.stl", "kinematics/gait_01.mot", "kinematics/static.mot",
              "kinematics/gait_01_marker_errors.sto", "kinematics/functional_hip.mot", "kinematics/crouch_000_01.mot"):
        assert (out / f).is_file(), f
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["errors"]["hip_centre_mm"]["fused"] == pytest.approx(summary["errors"]["hip_centre_mm"]["fused"])
    assert "static pose's facing" in on_disk["frame"] and on_disk["lab"]["up"] == "+Z"
    html = (out / "report.html").read_text()
    for text in ("Per-joint estimates", "Inverse kinematics", "Bones and landmarks", "<img"):
        assert text in html
    model = json.loads((out / "model.json").read_text())
    assert {b["name"] for b in model["bodies"]} >= {"pelvis", "femur_r", "tibia_l", "calcn_r", "toes_l"}
    assert model["knee_laws"]["r"]["joint"] == "knee_r"
    # the fused centres' covariances and axes' sds reach the model description
    unc = model["uncertainty"]["joints"]
    for s in summary["sides"]:
        for j in ("hip", "knee", "ankle"):
            f = summary["estimates"][f"{j}_{s}_centre"]["fused"]
            np.testing.assert_allclose(unc[f"{j}_{s}"]["centre"], f["mean"], rtol=1e-12)
            np.testing.assert_allclose(unc[f"{j}_{s}"]["centre_cov"], f["cov"], rtol=1e-12)
        assert unc[f"knee_{s}"]["axis_sd_deg"] == pytest.approx(summary["estimates"][f"knee_{s}_axis"]["fused"]["sd_deg"])
    # landmarks.json and joints.json are the `personalize bones` documents (one writer), input named
    assert json.loads((out / "joints.json").read_text())["input"].endswith("labels.nii.gz")
    assert "inputs" in json.loads((out / "landmarks.json").read_text())


def test_lengths_intercepts_and_chain_blend(subject):
    """Segment lengths and the knee law's intercept are fused and reported; the chains are blended per trial."""
    from kinematics.io.storage import read_mot

    subj, out, summary = subject
    est = summary["estimates"]
    truth = json.loads((subj / "truth.json").read_text())["joints"]["joints"]
    for s in summary["sides"]:
        for seg, (a, b) in (("thigh", ("hip", "knee")), ("shank", ("knee", "ankle"))):
            e = est[f"{seg}_{s}_length"]
            L = np.linalg.norm(np.subtract(truth[f"{a}_{s}"]["origin"], truth[f"{b}_{s}"]["origin"]))
            # the scanner-frame MRI length is precise (sub-mm sd): it takes the weight, the fused length is the bone's
            assert e["mri_sd"] < 1e-3 < e["motion_sd"] and e["fused"]["weights"]["mri"] > 0.95
            assert abs(e["fused"]["mean"][0] - L) < 2e-3
        t = est[f"knee_{s}_standing_translation"]
        f = np.asarray(t["fused"]["mean"])
        # the fused intercept shrinks the artefact-driven motion estimate towards the MRI's zero ...
        assert np.linalg.norm(f) < np.linalg.norm(t["motion"])
        assert abs(sum(t["fused"]["weights"].values()) - 1) < 1e-12 and t["fused"]["weights"]["mri"] > 0.5
        # ... and is the model's knee translation at the standing pose
        model = json.loads((out / "model.json").read_text())
        q = model["standing_q"]
        np.testing.assert_allclose([q[f"knee_t{a}_{s}"] for a in "xyz"], f, atol=1e-9)
    cb = summary["chain_blend"]
    assert set(cb["median_foot_to_hip_weight"]) == {"gait_01", "crouch_000_01"}
    for w in cb["median_foot_to_hip_weight"].values():
        assert all(0.0 <= v <= 1.0 for v in w.values())
    ang = read_mot(out / "kinematics" / "gait_01_chains.mot")
    assert ang.columns[0] == "hip_flexion_r" and np.isfinite(ang.values).mean() > 0.9
    assert set(cb["angle_rmse_deg_mean_over_angles"]) == {"pig", "foot-to-hip", "blend"}


def test_errors_against_truth(subject):
    _, _, summary = subject
    e = summary["errors"]
    assert set(e) >= {"hip_centre_mm", "knee_axis_deg", "ankle_axis_deg"}
    # MRI hip centres through the pelvis registration: a few mm; fused close to them
    assert e["hip_centre_mm"]["mri"] < 6.0
    assert e["hip_centre_mm"]["fused"] < 6.0
    assert e["hip_centre_mm"]["fused"] < e["hip_centre_mm"]["motion"]
    # the fused knee axis beats the skin-marker functional (SARA) axis on each side
    for side in summary["errors_per_side"].values():
        assert side["knee_axis_deg"]["fused"] < side["knee_axis_deg"]["motion"]
    assert e["knee_axis_deg"]["fused"] < 4.0
    assert e["ankle_axis_deg"]["fused"] < 4.0
    assert summary["truth_frame"]["scanner_to_static_lab_rms_m"] < 1e-6


def test_hips_fused_jointly_and_angle_errors(subject):
    _, _, summary = subject
    hj = summary["estimates"]["hips_joint_fusion"]
    assert set(hj["weights"]) == {"mri", "motion_r", "motion_l"} and hj["dof"] == 6
    assert hj["weights"]["mri"] > 0.8                     # the registration is the precise source of both hips
    C = np.array(hj["cov"])
    # both hips keep the shared registration error: correlated once the model-error term, independent per hip
    # (σ² I, the pelvic tissue measured in this phantom's skin label), is taken out
    from personalize.pipeline.hip import MRI_HIP_MODEL_SD_MEASURED

    v = MRI_HIP_MODEL_SD_MEASURED ** 2
    assert C[0, 0] > v and C[3, 3] > v
    assert C[0, 3] / np.sqrt((C[0, 0] - v) * (C[3, 3] - v)) > 0.3
    for s in "rl":
        w = summary["estimates"][f"hip_{s}_centre"]["fused"]["weights"]
        assert set(w) == {"mri", "motion"} and w["mri"] + w["motion"] == pytest.approx(1.0)
    a = summary["angle_rmse_deg"]
    assert {"hip_flexion_r", "knee_flexion_r", "ankle_angle_r", "knee_flexion_l"} <= set(a)
    # knee flexion follows the truth within a few degrees (soft-tissue artefact, personalised frames)
    assert 0.0 < a["knee_flexion_r"] < 8.0 and all(0.0 < v < 25.0 for v in a.values())
    off = summary["angle_offset_deg"]
    assert set(off) == set(a) and all(abs(off[c]) <= a[c] + 1e-9 for c in a)     # |mean| <= rms


def test_fuse_hips_cross_covariance():
    """fuse_hips: the MRI 6x6 covariance is the registration's J Cov Jᵀ blocks (scaled); weights per side sum to 1."""
    from lowerlimb.estimates import Gaussian
    from personalize.pipeline.hip import fuse_hips
    from personalize.registration import register_landmarks

    rng = np.random.default_rng(0)
    P = np.array([[0.12, 0.06, 0.0], [0.12, -0.06, 0.0], [-0.04, 0.05, 0.02], [-0.04, -0.05, 0.02]])
    reg = register_landmarks(P, P + [1.0, 0.5, 0.9] + rng.normal(0, 1e-3, P.shape), marker_sd=0.003)
    hips = {"r": Gaussian([0.05, -0.08, -0.08], 1e-8 * np.eye(3)), "l": Gaussian([0.05, 0.08, -0.08], 1e-8 * np.eye(3))}
    motion = {s: Gaussian(reg.transfer_point(h.mean)[0] + [0.005, 0.0, -0.01], 1e-4 * np.eye(3)) for s, h in hips.items()}
    mri, fused, joint = fuse_hips(reg, hips, motion, mri_scale=0.5)
    np.testing.assert_allclose(joint.weights.sum(axis=0), np.eye(6), atol=1e-12)
    np.testing.assert_allclose(mri["r"].cov, 0.5 * reg.transfer_estimate(hips["r"]).cov + 1e-8 * np.eye(3), rtol=1e-9)  # + detection floor
    Y, C6 = reg.transfer_points([hips["r"].mean, hips["l"].mean], [hips["r"].cov, hips["l"].cov])
    # the fused hips are closer to the (exact) MRI ones than to the 1 cm-off motion ones, and stay correlated
    for s in "rl":
        assert fused[s].shares.sum() == pytest.approx(1.0) and fused[s].shares[0] > 0.5
        assert np.linalg.norm(fused[s].mean - mri[s].mean) < np.linalg.norm(fused[s].mean - motion[s].mean)
    # the MRI hips enter with their cross-covariance: the fused hips stay correlated
    assert np.all(np.abs(np.diag(C6[:3, 3:])) > 0) and np.all(np.abs(np.diag(joint.cov[:3, 3:])) > 0)


def test_ik_every_trial(subject):
    subj, out, summary = subject
    assert set(summary["ik"]) == {"static", "gait_01", "crouch_000_01", "functional_hip"}
    # soft-tissue artefact of 5-20 mm on the thigh and shank: a few mm of residual, static nearly exact
    assert summary["ik"]["static"]["rms_mean_mm"] < 2.0
    assert 1.0 < summary["ik_rms_mm"] < 9.0
    from kinematics.io.storage import read_mot

    mot = read_mot(out / "kinematics" / "gait_01.mot")
    k = mot.column("knee_flexion_r")
    assert 40 < np.ptp(k) < 75          # degrees: the gait's knee flexion excursion (about 55 deg)


def test_deterministic(subject, tmp_path):
    subj, out, summary = subject
    again = run_subject(subj, tmp_path / "again", report=False)
    assert again["errors"] == summary["errors"]
    assert again["ik_rms_mm"] == summary["ik_rms_mm"]


# --------------------------------------------------------------------------- bad input
def _copy(subj, dst):
    shutil.copytree(subj, dst, ignore=shutil.ignore_patterns("truth"))
    return dst


def test_missing_static_exit_2(subject, tmp_path, capsys):
    subj, _, _ = subject
    bad = _copy(subj, tmp_path / "s")
    (bad / "static.c3d").unlink()
    assert main(["run", str(bad), "--out", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "static.c3d" in err and "missing" in err
    # the refusal is reported inside --out, and nothing else is written
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["report.html"]
    html = (tmp_path / "o" / "report.html").read_text()
    assert "refused" in html and "static.c3d" in html and "missing" in html


def test_missing_trials(subject, tmp_path):
    subj, _, _ = subject
    bad = _copy(subj, tmp_path / "s")
    for p in bad.glob("*.c3d"):
        if p.name != "static.c3d":
            p.unlink()
    with pytest.raises(InputError, match="no motion trial"):
        find_inputs(bad)


def test_trial_of_another_subject(subject, tmp_path, capsys):
    from kinematics.io.c3d import read_c3d, write_c3d
    from kinematics.io.markers import MarkerTrial

    subj, _, _ = subject
    bad = _copy(subj, tmp_path / "s")
    g = read_c3d(bad / "gait_01.c3d")
    c = np.nanmean(g.positions, axis=(0, 1))
    other = MarkerTrial(g.names, c + 1.1 * (g.positions - c), g.rate, g.time, "gait_02.c3d")   # a 10 % larger subject
    write_c3d(bad / "gait_02.c3d", other)
    assert main(["run", str(bad), "--out", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "gait_02.c3d" in err and "another subject" in err


def test_labels_and_markers_of_different_sides(tmp_path, capsys):
    from kinematics.io.c3d import read_c3d, write_c3d

    subj = write_phantom_subject(tmp_path / "s", seed=4, voxel_mm=3.0,
                                 bones=["pelvis", "femur_r", "tibia_r", "fibula_r", "patella_r", "talus_r", "calcn_r", "toes_r"])
    for p in subj.glob("*.c3d"):          # left-side markers only
        t = read_c3d(p)
        write_c3d(p, t.subset([n for n in t.names if not n.startswith("R") or n in ("RASI", "RPSI")]))
    assert main(["run", str(subj), "--out", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "side" in err


def test_plug_in_gait_marker_set_only(subject, tmp_path):
    """Standard Plug-in-Gait markers (no medial, cluster or device markers): fall-backs, still a valid model."""
    from kinematics.io.c3d import read_c3d, write_c3d

    subj, _, full = subject
    pig = tmp_path / "s"
    shutil.copytree(subj, pig)
    keep = {"ASI", "PSI", "THI", "KNE", "TIB", "ANK", "HEE", "TOE"}
    for p in pig.glob("*.c3d"):
        t = read_c3d(p)
        write_c3d(p, t.subset([n for n in t.names if n[1:] in keep]))
    s = run_subject(pig, tmp_path / "o", report=False)
    # one marker per knee / ankle: the femur's and shank's axial rotation from the virtual medial marker and knee axis
    assert s["sources"]["femur_r_axial_rotation"].startswith("virtual medial epicondyle marker")
    assert s["sources"]["tibia_l_axial_rotation"].startswith("the MRI knee flexion axis")
    assert any("no functional knee axis" in n for n in s["notes"])
    assert s["sources"]["hip_r_motion"].startswith("Plug-in-Gait (Davis)")    # no thigh cluster for SCoRE
    # the MRI hip centres do not depend on the thigh markers: same as with the full marker set
    assert s["errors"]["hip_centre_mm"]["mri"] == pytest.approx(full["errors"]["hip_centre_mm"]["mri"], abs=0.2)
    assert s["errors"]["hip_centre_mm"]["fused"] < 8.0
    assert s["errors"]["knee_axis_deg"]["fused"] < 12.0
    assert set(s["ik"]) == set(full["ik"]) and s["ik_rms_mm"] < 9.0


def test_knee_law_fitted_without_soft_tissue_artefact(subject):
    """Bone-fixed (STA-free) markers: the fitted law's flexion slopes match the phantom's true law."""
    from types import SimpleNamespace

    from kinematics.mechanisms.correlative import CorrelativeLaw
    from kinematics.io.opensim_io import load_osim
    from personalize.model_builder import GROUND_FROM_INTERNAL, default_knee_law
    from personalize.pipeline.knee_law import fit_knee_laws
    from phantoms import make_phantom
    from phantoms.motion import make_trials

    subj, out, summary = subject
    assert summary["sources"]["knee_law_r"].startswith("default law")        # skin markers: rejected
    pm = SimpleNamespace(model=load_osim(out / "model.osim"), knee_laws={"r": default_knee_law("r")},
                         G=GROUND_FROM_INTERNAL)
    _, trials, _ = make_trials(make_phantom(seed=SEED), SEED, gait_trials=1, gait_cycles=1.0, crouch_angles=(0,),
                               crouch_duration=2.0, functional_ranges=(45,), static_duration=0.3, sta=False)
    laws = fit_knee_laws(pm, [t.markers for t in trials if t.kind in ("gait", "crouch")])
    law, text = laws["r"]
    assert text.startswith("flexion slopes fitted")
    truth = CorrelativeLaw.from_json(json.loads((subj / "truth.json").read_text())["knee_law_r"])
    np.testing.assert_allclose(law.slopes[:2, 0], truth.slopes[:2, 0], atol=1.0e-3)   # m/rad, roll-back and sinking
    np.testing.assert_allclose(law.slopes[:, 1:], default_knee_law("r").slopes[:, 1:])


def test_markers_of_the_mirrored_side(subject, tmp_path, capsys):
    """R/L marker labels swapped relative to the MRI: refused by the registration's side check."""
    from kinematics.io.c3d import read_c3d, write_c3d
    from kinematics.io.markers import MarkerTrial

    subj, _, _ = subject
    bad = _copy(subj, tmp_path / "s")
    swap = {"R": "L", "L": "R"}
    for p in bad.glob("*.c3d"):
        t = read_c3d(p)
        write_c3d(p, MarkerTrial(tuple(swap.get(n[0], n[0]) + n[1:] for n in t.names), t.positions, t.rate, t.time, p.name))
    assert main(["run", str(bad), "--out", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "mirrored" in err and "static.c3d" in err
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["report.html"]
    assert "mirrored" in (tmp_path / "o" / "report.html").read_text()


# --------------------------------------------------------------------------- personalize demo
@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    from personalize.evaluation.demo import run_demo

    out = tmp_path_factory.mktemp("demo") / "out"
    return out, run_demo(out, seed=1, voxel_mm=2.0, short=True)


def test_demo_runs_the_pipeline(demo):
    out, summary = demo
    assert "surfaces" in summary and "femur_r" in summary["surfaces"]            # the surface table is kept
    p = summary["pipeline"]
    for key in ("hip_centre_mm", "knee_axis_deg", "ankle_axis_deg"):
        assert set(p["errors"][key]) == {"mri", "motion", "fused"}
    assert p["errors"]["hip_centre_mm"]["mri"] < 6.0 and p["errors"]["knee_axis_deg"]["fused"] < 4.0
    assert (out / "model" / "model.osim").is_file() and (out / "model" / "report.html").is_file()
    on_disk = json.loads((out / "model" / "summary.json").read_text())
    assert on_disk["ik_rms_mm"] == pytest.approx(p["ik_rms_mm"])


def test_demo_model_in_opensim(demo, opensim, tmp_path):
    """The demo's model.osim in OpenSim's conventions, and OpenSim's own IK tool on the written TRC and setup.

    Loaded with the opensim API: gravity (0, -9.80665, 0), the standing pelvis height in pelvis_ty; the TRC is in
    the model's ground (mm); OpenSim's IK tool on kinematics/gait_01_ik_setup.xml (a 0.25 s window) reproduces
    personalize's kinematics/gait_01.mot within 0.5 deg on every rotational coordinate (measured: 0.005 deg)."""
    from kinematics.io.opensim_io import run_opensim_ik_tool
    from kinematics.io.storage import read_mot, read_trc

    out, summary = demo
    om = opensim.Model(str(out / "model" / "model.osim"))
    s = om.initSystem()
    g = om.getGravity()
    assert [g.get(i) for i in range(3)] == pytest.approx([0.0, -9.80665, 0.0])
    cs = om.getCoordinateSet()
    assert cs.get("pelvis_ty").getValue(s) > 0.7            # the default (standing) pose: pelvis height, m
    trc = read_trc(out / "model" / "kinematics" / "gait_01.trc")
    assert trc.extra["units"] == "mm" and np.nanmedian(trc.marker("RASI")[:, 1]) > 0.7    # ground: Y up
    mine = read_mot(out / "model" / "kinematics" / "gait_01.mot")
    t0 = float(mine.time[10])
    ref = run_opensim_ik_tool(out / "model" / "kinematics" / "gait_01_ik_setup.xml", tmp_path, (t0, t0 + 0.25))
    rot = [cs.get(i).getName() for i in range(cs.getSize()) if int(cs.get(i).getMotionType()) == 1]
    assert len(ref["time"]) >= 20 and {"hip_flexion_r", "pelvis_tilt", "ankle_angle_l"} <= set(rot)
    for c in rot:
        q_os = np.degrees(ref["q"][:, ref["coordinates"].index(c)])
        q_me = np.interp(ref["time"], mine.time, mine.values[:, mine.columns.index(c)])
        assert np.max(np.abs(q_os - q_me)) < 0.5, c


def test_pelvic_soft_tissue_measured_in_the_mri(subject):
    """The phantom's label volume carries the skin: the tissue under the four pelvic markers is measured in it
    (source "MRI", within its sd of the drawn truth) and the measured-tissue covariance scale is in force."""
    subj, _, summary = subject
    truth = json.loads((subj / "truth.json").read_text())["image"]["skin"]["sites"]
    st = summary["skin_thickness"]
    assert set(st) == {"RASI", "LASI", "RPSI", "LPSI"}
    for k, v in st.items():
        assert v["source"] == "MRI"
        assert abs(v["thickness_mm"] - 1e3 * truth[k]["thickness"]) < max(v["sd_mm"], 1.5), (k, v, truth[k])
    from personalize.pipeline.hip import MRI_HIP_COV_SCALE_MEASURED

    assert summary["mri_hip_cov_scale"] == MRI_HIP_COV_SCALE_MEASURED


def test_implausible_pelvis_registration_is_flagged(subject, tmp_path):
    """Seed 2 draws a +3 sd ASIS soft tissue (54 mm).  With a bone-only label volume (the label map does not
    name the skin) the prior's scale is estimated with the registration (one scale for all sites: the markers
    cannot tell one thick site), but the MRI/motion hip disagreement can, and the summary says so.  With the skin label the tissue is measured and the MRI hip is
    right; the typical module subject raises no such note."""
    subj = write_phantom_subject(tmp_path / "thick", seed=2, voxel_mm=2.0)
    bone_only = tmp_path / "bone_only"
    shutil.copytree(subj, bone_only)
    lm = json.loads((bone_only / "label_map.json").read_text())
    assert lm.pop("skin") > 0
    (bone_only / "label_map.json").write_text(json.dumps(lm))
    summary = run_subject(bone_only, tmp_path / "out", report=False)
    assert summary["errors"]["hip_centre_mm"]["mri"] > 15.0
    # the tissue's scale is estimated with the registration (one scale: a single thick site stays unexplained)
    assert {v["source"] for v in summary["skin_thickness"].values()} == {"registration"}
    assert summary["registration"]["pelvis"]["tissue_scale"] > 0
    # with the tissue scale and the palpation sd the pelvis fit itself passes; the MRI and SCoRE hips disagree
    # (p 0.02 with the covariances calibrated on the realistic phantoms, where the MRI hip's stated sd is wider
    # than on the analytic ones: no longer below the 0.01 of the "hip centres disagree" note)
    assert summary["estimates"]["hip_r_centre"]["fused"]["p_value"] < 0.05
    assert summary["errors"]["hip_centre_mm"]["fused"] < summary["errors"]["hip_centre_mm"]["mri"]
    measured = run_subject(subj, tmp_path / "out_skin", report=False)
    truth = json.loads((subj / "truth.json").read_text())["image"]["skin"]["sites"]
    assert truth["RASI"]["thickness"] > 0.05
    assert measured["skin_thickness"]["RASI"]["source"] == "MRI"
    for k in ("RASI", "LASI"):
        m = measured["skin_thickness"][k]
        assert abs(m["thickness_mm"] - 1e3 * truth[k]["thickness"]) < m["sd_mm"], (k, m)
    assert measured["errors"]["hip_centre_mm"]["mri"] < 6.0
    assert not any(n.startswith("low confidence: pelvis") for n in measured["notes"])
    _, _, typical = subject
    assert not any(n.startswith("low confidence: pelvis") for n in typical["notes"])


def test_hip_angles_follow_the_anatomical_convention(subject):
    """Hip angles are femur-vs-pelvis frame angles (Plug-in-Gait/ISB), not zero at the static pose: the constant
    part of the error against the phantom's true angles is small (it was the ~10 deg pelvic tilt before)."""
    _, _, summary = subject
    for s in "rl":
        assert abs(summary["angle_offset_deg"][f"hip_flexion_{s}"]) < 3.0
        assert summary["angle_rmse_deg"][f"hip_flexion_{s}"] < 4.0


def test_calibration_constants_are_the_recorded_ones():
    """Every calibrated constant in force is the value calibration.json records with its source, and vice versa."""
    from personalize.pipeline.calibration import calibration_record, constants

    code, rec = constants(), calibration_record()
    assert set(code) == set(rec)
    for k, v in code.items():
        r = rec[k]["value"]
        if isinstance(v, dict):
            assert v == r, k
        else:
            np.testing.assert_allclose(v, r, rtol=1e-12, err_msg=k)
        assert rec[k]["benchmark"], k


def test_demo_model_and_meshes_are_light_and_stated(demo, opensim):
    """The demo's model.osim with its meshes under 20 MB; every mesh at most 20,000 faces (the STL's own count),
    watertight where its surface was, its decimation error stated (model.json, STL header, the .osim's credits)."""
    from personalize.model_builder import MODEL_MESH_MAX_FACES

    out, _ = demo
    m = out / "model"
    size = (m / "model.osim").stat().st_size + sum(f.stat().st_size for f in (m / "meshes").iterdir())
    assert size < 20e6
    doc = json.loads((m / "model.json").read_text())["mesh_files"]
    assert len(doc) >= 13 and sum(v["decimated"] for v in doc.values()) >= 5
    for bone, v in doc.items():
        data = (m / v["file"]).read_bytes()
        n = int.from_bytes(data[80:84], "little")
        assert n == v["faces"] <= MODEL_MESH_MAX_FACES and len(data) == 84 + 50 * n, bone
        assert data[:80].decode().startswith(f"m; body {v['body']} frame;")
        assert v["units"] == "m" and v["source"].endswith(f"labels.nii.gz: {bone}")
        assert v["watertight"]["written"] or not v["watertight"]["source"], bone
        if v["decimated"]:
            assert v["source_faces"] > v["faces"] and 0 < v["mean_distance_mm"] < 0.1, (bone, v)
            assert v["hausdorff_mm"] < 1.0, (bone, v)                     # 2 mm voxels
    om = opensim.Model(str(m / "model.osim"))
    assert "quadric edge collapse" in om.getCredits() and "metres" in om.getCredits()
    assert om.getBodySet().get("pelvis").getPropertyByName("attached_geometry").size() == 1


def test_setup_writers_on_the_demo_model(demo, opensim, tmp_path):
    """Without force plates (the analytic phantom has none), the set-up writers on the demo's model and gait IK with
    a synthetic ground reaction on calcn_r: OpenSim's ID and SO run as written; ID = personalize's ID, SO = ID."""
    from kinematics.io.dynamics_setup import run_setup, write_reserve_actuators, write_so_setup
    from kinematics.io.storage import read_sto
    from opensim_checks import check_so_reproduces_id, generalised_force, synthetic_load_id_against_opensim

    out, _ = demo
    opensim.Logger.setLevelString("warn")
    k, os_id, common = synthetic_load_id_against_opensim(out / "model", tmp_path)
    write_reserve_actuators(tmp_path / "reserve_actuators.xml", tmp_path / "model.osim")
    write_so_setup(k / "so.xml", force_set_files=["../reserve_actuators.xml"], name="so", **common)
    assert np.abs(generalised_force(os_id, "ankle_angle_r")).max() > 10.0        # the load reaches the foot
    assert run_setup(k / "so.xml") == "AnalyzeTool"
    so = read_sto(k / "so_StaticOptimization_force.sto")
    check_so_reproduces_id(json.loads((tmp_path / "model.json").read_text()), os_id, so)
