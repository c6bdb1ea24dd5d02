"""The personalised model against gait2392 scaled to the same markers (issue M1, `personalize.generic_comparison`):
the scaling pairs, the placement markers, and a phantom run checked against OpenSim and the phantom's truth."""
from __future__ import annotations

import json

import numpy as np
import pytest


def test_scaling_pairs_fall_back_as_opensims_example_does():
    """No trochanter marker: the thigh from ASIS-knee; the foot always with the shank (gait2392's metatarsal-head
    landmarks are misplaced); with trochanters, OpenSim's trochanter-knee pairs."""
    from personalize.generic_comparison import _measurement_set

    pig = {"RASI", "LASI", "RPSI", "LPSI", "RKNE", "LKNE", "RANK", "LANK", "RHEE", "LHEE", "RD1M"}
    m, notes = _measurement_set(pig)
    assert m["thigh"][0] == [("RASI", "RKNE"), ("LASI", "LKNE")]
    assert m["pelvis"][0] == [("RASI", "LASI"), ("RASI", "RPSI"), ("LASI", "LPSI")]
    assert "foot" not in m and {"calcn_r", "toes_l"} <= set(m["shank"][1])
    assert len(notes) == 2
    m, notes = _measurement_set(pig | {"RTRO", "LTRO"})
    assert m["thigh"][0] == [("RTRO", "RKNE"), ("LTRO", "LKNE")] and len(notes) == 1


def test_placement_markers_are_the_scaled_landmarks():
    from personalize.generic_comparison import _placement_markers

    lm = {"pelvis": {"RASI": [0.0, 0.0, 0.1], "RPSI": [-0.15, 0.0, 0.04], "LPSI": [-0.15, 0.0, -0.04]},
          "femur_r": {"KNE": [0.0, -0.4, 0.05], "femoral_head_centre": [0.0, 0.0, 0.0]},
          "calcn_r": {"HEE": [-0.01, 0.0, 0.0], "D1M": [0.15, 0.0, -0.02]}}
    out = {m.name: m for m in _placement_markers(lm, {"pelvis": 0.8, "femur_r": 1.1, "calcn_r": 1.0},
                                                 {"RASI", "SACR", "RKNE", "RHEE", "RD1M", "LPSI"})}
    assert set(out) == {"RASI", "SACR", "RKNE", "RHEE", "LPSI"}          # D1M left out, unwanted names too
    assert np.allclose(out["SACR"].offset, [-0.12, 0.0, 0.0]) and out["SACR"].body == "pelvis"
    assert np.allclose(out["RKNE"].offset, [0.0, -0.44, 0.055]) and out["RKNE"].body == "femur_r"


@pytest.fixture(scope="module")
def generic_run(shared_data, opensim, tmp_path_factory):
    """The analytic phantom (Plug-in-Gait) run with the comparison: (output folder, summary, subject folder)."""
    from personalize.evaluation.phantom_builder import PhantomOptions, build_phantom, write_phantom
    from personalize.pipeline import run_subject

    root = tmp_path_factory.mktemp("generic")
    subject, out = root / "subject", root / "out"
    write_phantom(build_phantom(PhantomOptions(seed=5, static_frames=20, functional=False)), subject)
    summary = run_subject(subject, out, report=True, muscles="none", generic=True,
                          gait2392=shared_data / "opensim_gait2392" / "gait2392_thelen2003muscle.osim")
    return out, summary, subject


def test_opensims_ik_tool_reproduces_the_generic_ik(generic_run):
    from opensim_checks import opensim_ik_difference_deg

    out, summary, _ = generic_run
    trial = next(iter(summary["generic"]["trials"]))
    worst, _ = opensim_ik_difference_deg(out / "generic" / f"{trial}_ik_setup.xml", out / "generic" / f"{trial}.mot",
                                         out / "opensim_check", out / "generic" / "scaled_generic.osim")
    assert worst < 0.05


def test_scale_factors_are_scaletools_pair_ratios(generic_run, shared_data):
    """The pelvis factor is the mean of subject / gait2392 distances over the pelvis pairs (ScaleTool's rule),
    recomputed from the static trial and gait2392's own landmarks."""
    from kinematics.io.storage import read_trc
    from personalize.muscles.generic import load_generic_model

    out, summary, _ = generic_run
    g = summary["generic"]
    st = read_trc(out / "kinematics" / "static.trc")
    x = {n: np.nanmean(st.positions[:, k], axis=0) for k, n in enumerate(st.names)}
    lm = load_generic_model(shared_data / "opensim_gait2392" / "gait2392_thelen2003muscle.osim").landmarks["pelvis"]
    ratios = [np.linalg.norm(x[a] - x[b]) / np.linalg.norm(np.subtract(lm[a], lm[b])) for a, b in g["measurements"]["pelvis"]]
    assert len(ratios) == 3
    assert g["scale_factors"]["pelvis"] == pytest.approx(np.mean(ratios), rel=1e-4)


def test_reported_centres_are_the_models_joints_in_opensim(generic_run, opensim):
    """Both models' centres as OpenSim places the joints: model.osim in its default (static) pose, the scaled
    gait2392 in its placement pose (generic/static.mot)."""
    from kinematics.io.storage import read_mot

    out, summary, _ = generic_run
    cen = summary["generic"]["centres"]

    def joint_centres(model, pose=None):
        state = model.initSystem()
        if pose is not None:
            for c in model.getCoordinateSet():
                if c.getName() in pose.columns:
                    v = pose.values[0, pose.columns.index(c.getName())]
                    c.setValue(state, np.radians(v) if pose.in_degrees and c.getMotionType() == 1 else v, False)
            model.assemble(state)
        model.realizePosition(state)
        return {j: np.array([model.getJointSet().get(j).getChildFrame().getPositionInGround(state).get(i)
                             for i in range(3)]) for j in cen}

    p = joint_centres(opensim.Model(str(out / "model.osim")))
    g = joint_centres(opensim.Model(str(out / "generic" / "scaled_generic.osim")), read_mot(out / "generic" / "static.mot"))
    for j, v in cen.items():
        assert np.linalg.norm(p[j] - v["personalised_m"]) < 1e-4
        assert np.linalg.norm(g[j] - v["generic_m"]) < 1e-4


def test_personalised_knees_are_nearer_the_truth_than_the_scaled_generic(generic_run):
    """What the MRI buys on a phantom: the knee centres (the joint gait2392's scaling misplaces most)."""
    out, summary, _ = generic_run
    err = summary["generic"]["truth"]["centre_error_mm"]
    print(json.dumps(err, indent=1))
    for s in ("r", "l"):
        assert err[f"knee_{s}"]["personalised"] < err[f"knee_{s}"]["generic"]
    assert (out / "generic" / "scaled_generic.osim").is_file()
    assert "scaled gait2392" in (out / "report.html").read_text(encoding="utf-8")
