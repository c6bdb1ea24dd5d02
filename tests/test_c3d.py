"""C3D reading/writing and gap filling."""
from __future__ import annotations

import numpy as np
import pytest

from kinematics.io.c3d import fill_gaps, read_c3d, read_c3d_outputs, write_c3d
from lowerlimb.errors import InputError
from kinematics.io.markers import MarkerTrial
from kinematics.gait.subject import read_subject, read_vsk


def _trial(F=200, rate=100.0):
    t = np.arange(F) / rate
    a = np.stack([np.sin(2 * np.pi * t), np.cos(2 * np.pi * t), 1 + 0.1 * t], 1)
    b = np.stack([0.5 * t, 0.2 * np.sin(np.pi * t), 0.9 + 0 * t], 1)
    return MarkerTrial(("A", "B"), np.stack([a, b], 1), rate, t, "synthetic")


def test_write_read_round_trip(tmp_path):
    tr = _trial()
    pos = tr.positions.copy()
    pos[10:15, 0] = np.nan
    tr = MarkerTrial(tr.names, pos, tr.rate, tr.time, "x")
    p = write_c3d(tmp_path / "t.c3d", tr)
    back = read_c3d(p)
    assert back.names == tr.names and back.rate == tr.rate
    np.testing.assert_array_equal(np.isnan(back.positions), np.isnan(tr.positions))
    # file stores float32 millimetres
    np.testing.assert_allclose(back.positions, tr.positions, atol=1e-6, equal_nan=True)
    assert back.extra["units_in_file"] == "mm"
    assert not list(tmp_path.glob(".*partial*"))  # atomic: no temporary left


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_c3d(tmp_path / "none.c3d")
    bad = tmp_path / "bad.c3d"
    bad.write_bytes(b"not a c3d file at all" * 10)
    with pytest.raises(InputError):
        read_c3d(bad)


def test_nan_with_a_valid_residual_is_a_gap_and_infinity_is_refused(tmp_path):
    import ezc3d

    trial = MarkerTrial(("A", "B"), np.ones((20, 2, 3)), 100.0, np.arange(20) / 100.0, "t")
    write_c3d(tmp_path / "t.c3d", trial)
    c = ezc3d.c3d(str(tmp_path / "t.c3d"))
    pts = np.array(c["data"]["points"], float)
    pts[0, 1, 5] = np.nan                 # residual stays 0 (valid): a float exporter's gap
    c["data"]["points"] = pts
    c.write(str(tmp_path / "nan.c3d"))
    got = read_c3d(tmp_path / "nan.c3d")
    assert np.isnan(got.positions[5, 1]).all() and np.isfinite(np.delete(got.positions, 5, axis=0)).all()
    assert np.isfinite(got.positions[:, 0]).all()
    pts[0, 1, 5] = np.inf
    c["data"]["points"] = pts
    c.write(str(tmp_path / "inf.c3d"))
    with pytest.raises(InputError, match=r"inf\.c3d: 1 sample\(s\) marked valid are not finite"):
        read_c3d(tmp_path / "inf.c3d")


def test_fill_short_gaps_report_long_ones():
    tr = _trial()
    pos = tr.positions.copy()
    truth = pos.copy()
    pos[50:54, 0] = np.nan  # 4 frames = 0.04 s: filled
    pos[100:140, 0] = np.nan  # 0.4 s: too long
    pos[:3, 1] = np.nan  # leading gap: never extrapolated
    filled, report = fill_gaps(MarkerTrial(tr.names, pos, tr.rate, tr.time, "g"), max_gap_s=0.1)
    np.testing.assert_allclose(filled.positions[50:54, 0], truth[50:54, 0], atol=1e-4)  # 1 m, 1 Hz sine: spline within 0.1 mm
    assert np.all(np.isnan(filled.positions[100:140, 0]))
    assert np.all(np.isnan(filled.positions[:3, 1]))
    reasons = {(g.marker, g.n_frames): g.reason for g in report.gaps}
    assert reasons == {("A", 4): "filled", ("A", 40): "too long", ("B", 3): "at trial start/end"}
    assert "2 left as NaN" in report.summary()
    with pytest.raises(InputError):
        fill_gaps(tr, -1)


def test_read_nexus_markers_and_outputs(shared_data):
    d = shared_data / "mocap_pig"
    tr = read_c3d(d / "Movement_trial.c3d")
    out = read_c3d_outputs(d / "Movement_trial.c3d")
    assert tr.rate == 120.0 and "RASI" in tr.names and "RFEO" in tr.names
    assert not any(n.startswith("*") for n in tr.names)
    assert "RKneeAngles" not in tr.names and "RKneeAngles" in out.values  # angles are not markers
    # metres: the ASIS markers are about 0.2-0.4 m apart
    iad = np.nanmedian(np.linalg.norm(tr.marker("RASI") - tr.marker("LASI"), axis=1))
    assert 0.2 < iad < 0.4
    # angles are radians: knee flexion of a walking/moving subject stays within (-0.5, 2.6) rad
    kf = out["RKneeAngles"][:, 0]
    assert np.nanmax(np.abs(kf)) < 2.6 and out.units["RKneeAngles"] == "rad"
    assert out.units["RKneeMoment"] == "N m"
    with pytest.raises(InputError, match="not in the file"):
        out["NoSuchAngle"]


def test_read_vsk(shared_data):
    s = read_vsk(shared_data / "mocap_pig" / "Test.vsk")
    assert s.right_leg_length == pytest.approx(0.866) and s.left_leg_length == pytest.approx(0.877)
    assert s.inter_asis_distance == pytest.approx(0.306) and s.mass == pytest.approx(85)
    assert s.right_knee_width == pytest.approx(0.139) and s.left_ankle_width == pytest.approx(0.085)
    assert s.marker_diameter == pytest.approx(0.014)  # not in the vsk: Vicon default
    assert s.right_tibial_torsion == 0.0  # empty value in the vsk


def test_subject_json_round_trip_and_errors(tmp_path):
    from kinematics.gait.subject import SubjectMeasurements

    s = SubjectMeasurements(0.9, 0.9, 0.1, 0.1, 0.07, 0.07, inter_asis_distance=0.25, mass=70.0)
    p = tmp_path / "s.json"
    p.write_text(s.to_json())
    assert read_subject(p).left_leg_length == 0.9
    p.write_text('{"left_leg_length": 900, "right_leg_length": 0.9, "left_knee_width": 0.1, "right_knee_width": 0.1,'
                 ' "left_ankle_width": 0.07, "right_ankle_width": 0.07}')
    with pytest.raises(InputError, match="mm given as m"):
        read_subject(p)
    p.write_text('{"left_leg_length": 0.9}')
    with pytest.raises(InputError, match="missing subject measurements"):
        read_subject(p)
    bad = tmp_path / "x.vsk"
    bad.write_text('<?xml version="1.0"?><!DOCTYPE a [<!ENTITY e "boom">]><a>&e;</a>')
    with pytest.raises(InputError):  # defusedxml refuses entity declarations
        read_subject(bad)


def test_outputs_round_trip_in_degrees(tmp_path):
    from kinematics.io.c3d import C3DOutputs

    tr = _trial(F=20)
    ang = np.radians(np.stack([np.linspace(0, 60, 20), np.zeros(20), np.full(20, -5.0)], 1))
    out = C3DOutputs({"RKneeAngles": ang}, {"RKneeAngles": "ANGLES"}, {"RKneeAngles": "rad"}, tr.rate)
    p = write_c3d(tmp_path / "o.c3d", tr, outputs=out)
    import ezc3d

    raw = ezc3d.c3d(str(p))
    assert raw["parameters"]["POINT"]["ANGLE_UNITS"]["value"] == ["deg"]
    back = read_c3d_outputs(p)
    np.testing.assert_allclose(back["RKneeAngles"], ang, atol=1e-6)
    assert read_c3d(p).names == tr.names  # angles are not read back as markers
