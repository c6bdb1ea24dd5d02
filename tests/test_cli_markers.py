"""``personalize markers``: outputs against the motion phantom's truth, and bad input."""
from __future__ import annotations

import json

import numpy as np
import pytest

from kinematics.io.c3d import read_c3d, write_c3d
from kinematics.io.storage import read_mot, read_trc
from personalize.cli import main
from phantoms import make_phantom
from phantoms.motion import write_trials


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    d = tmp_path_factory.mktemp("phantom_motion")
    write_trials(d, make_phantom(0), 0, rate=100, gait_trials=1, gait_cycles=1.5, crouch_angles=(), functional_ranges=(45,),
                 functional_time_scale=0.5, gaps=True)
    return d


def _run(lab, out, method, *extra):
    return main(["markers", str(lab / "gait_01.c3d"), "--method", method, "--subject", str(lab / "subject.json"),
                 "--static", str(lab / "static.c3d"), "--out", str(out), *extra])


@pytest.mark.parametrize("method", ["pig", "foot-to-hip", "blend"])
def test_outputs_match_the_phantom_truth(lab, tmp_path, method):
    out = tmp_path / method
    assert _run(lab, out, method, "--functional", str(lab / "functional_hip.c3d")) == 0
    assert sorted(p.name for p in out.iterdir()) == ["angles.mot", "angles.png", "centres.trc", "report.json"]
    ang = read_mot(out / "angles.mot")
    truth = read_mot(lab / "truth" / "gait_01_angles.mot")
    assert ang.columns == truth.columns and ang.in_degrees
    assert ang.columns[:3] == ("hip_flexion_r", "hip_adduction_r", "hip_rotation_r")
    for col, tol in (("knee_flexion_r", 6.0), ("hip_flexion_r", 6.0), ("knee_flexion_l", 6.0), ("ankle_flexion_r", 6.0)):
        j = ang.columns.index(col)
        e = ang.values[:, j] - truth.values[:, j]
        assert np.sqrt(np.nanmean(e**2)) < tol, (col, e)
    cen = read_trc(out / "centres.trc")
    assert cen.names == ("RHJC", "LHJC", "RKJC", "LKJC", "RAJC", "LAJC")
    tc = read_trc(lab / "truth" / "gait_01_centres.trc")
    e = np.linalg.norm(cen.positions - tc.positions, axis=2)
    assert np.nanmean(e[:, 0]) < 0.03 and np.nanmean(e[:, 2]) < 0.03
    rep = json.loads((out / "report.json").read_text())
    assert rep["method"] == method and set(rep["hip_in_pelvis"]) == {"R", "L"}
    # the long gap is reported, never invented: the frames of that marker's side are NaN
    long = [g for g in rep["gaps"] if g["trial"] == "gait_01.c3d" and not g["filled"]]
    assert long and long[0]["reason"] == "too long"
    g = long[0]
    side = "r" if g["marker"][0] == "R" else "l"
    frames = (ang.time >= g["start_s"] - 1e-9) & (ang.time <= g["end_s"] + 1e-9)
    affected = [j for j, c in enumerate(ang.columns) if c.endswith(f"_{side}") and c.startswith("knee")]
    # a blend loses a frame only when both chains do (a marker both use)
    used = {"pig": ("THI", "KNE", "TIB", "ANK"), "foot-to-hip": ("THI", "KNE", "ANK", "HEE", "TOE"),
            "blend": ("THI", "KNE", "ANK")}[method]
    if g["marker"][1:] in used:
        assert np.isnan(ang.values[np.ix_(frames, affected)]).all()
    else:
        assert np.isfinite(ang.values[np.ix_(frames, affected)]).all()
    assert np.isfinite(ang.values[~frames][:, affected]).all()
    short = [g for g in rep["gaps"] if g["trial"] == "gait_01.c3d" and g["filled"]]
    assert short and short[0]["frames"] == 5


def test_missing_markers_are_named(lab, tmp_path, capsys):
    tr = read_c3d(lab / "gait_01.c3d")
    keep = [n for n in tr.names if n not in ("RTOE", "LKNE")]
    bad = tmp_path / "bad.c3d"
    write_c3d(bad, tr.subset(keep))
    code = main(["markers", str(bad), "--method", "foot-to-hip", "--subject", str(lab / "subject.json"),
                 "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and "RTOE" in err and "LKNE" in err
    assert not (tmp_path / "o").exists()


def test_static_of_another_subject_is_refused(lab, tmp_path, capsys):
    other = tmp_path / "other"
    other.mkdir()
    write_trials(other, make_phantom(4, stature=1.45), 4, rate=20, gait_trials=0, crouch_angles=(), functional_ranges=(),
                 static_duration=0.5)
    code = main(["markers", str(lab / "gait_01.c3d"), "--method", "pig", "--subject", str(lab / "subject.json"),
                 "--static", str(other / "static.c3d"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and "leg length" in err and "another subject" in err
    assert not (tmp_path / "o").exists()


def test_usage_errors(lab, tmp_path, capsys):
    assert main(["markers", str(lab / "gait_01.c3d"), "--method", "pig", "--out", str(tmp_path / "o")]) == 2
    assert "--subject" in capsys.readouterr().err
    assert _run(lab, tmp_path / "o", "davis") == 2
    assert "davis" in capsys.readouterr().err
    assert main(["markers", str(lab / "nope.c3d"), "--method", "pig", "--subject", str(lab / "subject.json"),
                 "--out", str(tmp_path / "o")]) == 2
    assert "not found" in capsys.readouterr().err


def test_leg_reconstruction_from_a_script(lab, tmp_path):
    """The library form of the command (reconstruct_legs, leg_report) and the trial reader it uses."""
    from kinematics.io.storage import write_trc
    from kinematics.io.trials import read_trial
    from lowerlimb.errors import InputError
    from personalize.leg_reconstruction import leg_report, reconstruct_legs

    res = reconstruct_legs(lab / "gait_01.c3d", method="pig", subject=lab / "subject.json", static=lab / "static.c3d")
    truth = read_mot(lab / "truth" / "gait_01_angles.mot")
    j = truth.columns.index("knee_flexion_r")
    e = np.degrees(res.reconstruction.angle_table()[:, j]) - truth.values[:, j]
    assert np.sqrt(np.nanmean(e ** 2)) < 6.0
    rep = leg_report(res)
    assert rep["valid_frames"] == res.valid_frames < res.frames == rep["frames"]     # the long gap stays NaN
    assert any(not g["filled"] for g in rep["gaps"]) and json.loads(json.dumps(rep)) == rep
    tr = read_trial(lab / "gait_01.c3d")
    write_trc(tmp_path / "gait.trc", tr)
    back = read_trial(tmp_path / "gait.trc")
    assert back.names == tr.names
    np.testing.assert_allclose(back.positions, tr.positions, atol=1e-5)
    (tmp_path / "gait.txt").write_text("x")
    with pytest.raises(InputError, match="unsupported marker file type '.txt'"):
        read_trial(tmp_path / "gait.txt")


def test_lab_is_read_from_the_pig_trials(shared_data, tmp_path, capsys):
    """mocap_pig (Z-up C3D, Plug-in-Gait): the lab line names +Z up and the -X walk; the library result holds it."""
    from personalize.leg_reconstruction import reconstruct_legs

    d = shared_data / "mocap_pig"
    code = main(["markers", str(d / "Movement_trial.c3d"), "--method", "pig", "--subject", str(d / "Test.vsk"),
                 "--static", str(d / "Static_trial.c3d"), "--out", str(tmp_path / "o"), "--no-plot"])
    assert code == 0
    assert "lab: Z up, walking -X, floor at -0.158 m" in capsys.readouterr().err
    res = reconstruct_legs(d / "Movement_trial.c3d", method="pig", subject=d / "Test.vsk")
    np.testing.assert_array_equal(res.lab.up, [0, 0, 1])
    assert res.lab.forward @ [-1, 0, 0] > np.cos(np.radians(5)) and res.lab_problem == ""


def test_lab_of_the_phantom(lab, tmp_path, capsys):
    """The motion phantom's lab is Z up; its gait trial walks along +X."""
    assert _run(lab, tmp_path / "o", "pig", "--no-plot") == 0
    assert "lab: Z up, walking +X" in capsys.readouterr().err
