"""gait2392's muscles on the subject's bones (issue M1): the pieces on their own, and the pipeline's model against
gait2392 scaled to the same subject by OpenSim's ScaleTool."""
from __future__ import annotations

import numpy as np
import pytest


def test_umeyama_recovers_a_similarity():
    from scipy.spatial.transform import Rotation

    from personalize.muscles.bone_registration import umeyama

    rng = np.random.default_rng(0)
    P = rng.normal(size=(50, 3))
    R = Rotation.from_rotvec([0.2, -0.5, 0.3]).as_matrix()
    Q = 1.3 * P @ R.T + [0.1, -0.2, 0.3]
    s, Rf, t = umeyama(P, Q)
    assert s == pytest.approx(1.3) and np.allclose(Rf, R) and np.allclose(t, [0.1, -0.2, 0.3])


def test_bone_registration_finds_a_scaled_turned_bone(shared_data):
    """The generic femur, scaled 1.1, turned 10 deg about its long axis and moved, is found again from its joints."""
    from scipy.spatial.transform import Rotation

    from personalize.muscles.bone_registration import register_bone, similarity_from_joints
    from personalize.muscles.generic import load_generic_model

    g = load_generic_model(shared_data / "opensim_gait2392" / "gait2392_thelen2003muscle.osim")
    A = 1.1 * Rotation.from_rotvec([0.0, np.radians(10.0), 0.0]).as_matrix()
    t = np.array([0.01, 0.44, -0.02])
    subject = g.meshes["femur_r"].copy()
    subject.vertices = np.asarray(subject.vertices) @ A.T + t
    gj = g.joint_points["femur_r"]
    sj = {k: A @ v + t for k, v in gj.items()}
    m = register_bone("femur_r", g.meshes["femur_r"], subject, similarity_from_joints(gj, sj),
                      [(gj[k], sj[k]) for k in gj])
    x = np.asarray(g.meshes["femur_r"].vertices)
    assert np.abs(m(x) - (x @ A.T + t)).max() < 2e-3
    assert m.distances_mm[m.kind] < 1.0


def test_pipeline_muscles_match_scaled_gait2392(shared_data, opensim, tmp_path):
    """The ICL-MRI phantom's model: OpenSim loads its 86 muscles; MTU lengths and hip, knee, ankle moment arms
    against gait2392 scaled by OpenSim's ScaleTool (fractions within 15 % printed; asserted at the levels this
    first version reaches, see benchmarks/muscles.py)."""
    from muscles import build

    from personalize.muscles.compare import compare_run, table

    subject, model = build(tmp_path)
    m = opensim.Model(str(model / "model.osim"))
    m.initSystem()
    assert m.getMuscles().getSize() == 86
    res = compare_run(model, subject, tmp_path / "scale", n=5)
    print(table(res))
    f = res["fractions"]
    assert res["counts"]["length"] == 43
    assert f["hip_flexion"] >= 0.75
    assert f["length"] >= 0.68
    assert f["knee_angle"] >= 0.5
    assert f["ankle_angle"] >= 0.4
    rep = __import__("json").loads((model / "muscles.json").read_text(encoding="utf-8"))
    tib = rep["bodies"]["tibia_r"]
    assert tib["twist"] is not None and abs(tib["twist"]["deg_between_joints"]) > 10.0   # ICL's tibial torsion
    assert tib["landmark_residual_mm"]["TTB"] < 10.0
    _check_moment_arms_against_opensim(m)


def _check_moment_arms_against_opensim(model):
    """The benchmark's moment arms, -dL/dq by central differences with the knee's coupled translations following
    (`compare._moment_arms`), are OpenSim's own `Muscle.computeMomentArm` on the personalised model."""
    from personalize.muscles.calibration import mtu_lengths
    from personalize.muscles.compare import _H, _moment_arms
    from personalize.muscles.poses import _couplers, set_pose

    state = model.initSystem()
    mus = ["vas_med_r", "rect_fem_r", "bifemsh_r", "semimem_r", "lat_gas_r", "glut_max1_r", "iliacus_r", "soleus_r",
           "tib_ant_r", "sar_r", "add_long_r", "grac_r"]
    worst = 0.0
    for coord, values in (("knee_flexion_r", (0.2, 0.8, 1.3)), ("hip_flexion_r", (-0.2, 0.3, 0.9)),
                          ("ankle_angle_r", (-0.2, 0.1))):
        for v in values:
            ours = _moment_arms(mtu_lengths(model, mus, [{coord: v}, {coord: v - _H}, {coord: v + _H}], state))[0]
            set_pose(model, state, {coord: v}, _couplers(model))
            c = model.getCoordinateSet().get(coord)
            theirs = np.array([model.getMuscles().get(n).computeMomentArm(state, c) for n in mus])
            assert np.max(np.abs(theirs)) > 0.03
            worst = max(worst, float(np.max(np.abs(ours - theirs))))
    assert worst < 5e-5


def test_default_muscles_that_fail_leave_the_model_without_them(shared_data, opensim, monkeypatch, tmp_path):
    """By default the muscles are an addition: when carrying them fails the model is still written, without
    them, with a note (asked for, ``muscles="gait2392"``, the failure stops the run: `_run_subject`)."""
    import personalize.muscles as muscles_pkg
    from personalize.evaluation.phantom_subject import write_phantom_subject
    from personalize.pipeline import run_subject

    def fail(*args, **kwargs):
        raise RuntimeError("registration diverged")

    subj = write_phantom_subject(tmp_path / "subject", seed=5, voxel_mm=2.0)
    monkeypatch.delenv("PERSONALIZE_MUSCLES", raising=False)
    monkeypatch.setattr(muscles_pkg, "personalise_muscles", fail)
    summary = run_subject(subj, tmp_path / "out", report=False)
    assert any("no muscles" in n and "registration diverged" in n for n in summary["notes"])
    assert not (tmp_path / "out" / "muscles.json").exists()
    m = opensim.Model(str(tmp_path / "out" / "model.osim"))
    m.initSystem()
    assert m.getMuscles().getSize() == 0 and m.getBodySet().getSize() > 5


@pytest.mark.parametrize("args, env, named", [(["--muscles", "foo"], None, "--muscles"),
                                               (["--gait2392", "missing.osim"], None, "missing.osim"),
                                               ([], "maybe", "PERSONALIZE_MUSCLES")])
def test_bad_muscle_options_are_refused_before_any_work(tmp_path, monkeypatch, capsys, args, env, named):
    """A bad --muscles, a missing --gait2392 file or a bad $PERSONALIZE_MUSCLES: one line naming it, exit 2,
    nothing written (checked before the subject is read)."""
    from personalize.cli import main

    (tmp_path / "subject").mkdir()
    if env is None:
        monkeypatch.delenv("PERSONALIZE_MUSCLES", raising=False)
    else:
        monkeypatch.setenv("PERSONALIZE_MUSCLES", env)
    assert main(["run", str(tmp_path / "subject"), "--out", str(tmp_path / "o"), "-q", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert named in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()
