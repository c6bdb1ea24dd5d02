"""``personalize scale`` against OpenSim's own ScaleTool on gait2392 / subject01 (../shared/data/opensim_gait2392).

OpenSim's ScaleTool runs on the same setup (``subject01_Setup_Scale.xml``, its file names redirected to the
data and to a temporary folder); its scale factors are read from the scale set it writes, its marker RMS is
recomputed with the opensim API from the model it wrote before placing markers and the static pose it solved.
"""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from personalize.cli import main

DATA = "opensim_gait2392"


def _files(shared_data):
    d = shared_data / DATA
    f = {"static": d / "subject01_static.trc", "model": d / "gait2392_thelen2003muscle.osim",
         "setup": d / "subject01_Setup_Scale.xml", "marker_set": d / "gait2392_Scale_MarkerSet.xml"}
    for p in f.values():
        if not p.is_file():
            pytest.skip(f"{p} not in the shared data")
    return f


@pytest.fixture(scope="module")
def scale_runs(shared_data, opensim, tmp_path_factory):
    """(our output folder, ScaleTool's output folder, the input files)."""
    f = _files(shared_data)
    ours = tmp_path_factory.mktemp("ours") / "scaled"
    assert main(["scale", str(f["static"]), "--model", str(f["model"]), "--setup", str(f["setup"]),
                 "--marker-set", str(f["marker_set"]), "--out", str(ours), "--quiet"]) == 0

    ref = tmp_path_factory.mktemp("scaletool")
    opensim.Logger.setLevel(opensim.Logger.Level_Error)
    tool = opensim.ScaleTool(os.fspath(f["setup"]))
    tool.setPathToSubject("")                       # every name below is absolute
    gmm = tool.getGenericModelMaker()
    gmm.setModelFileName(os.fspath(f["model"]))
    gmm.setMarkerSetFileName(os.fspath(f["marker_set"]))
    ms = tool.getModelScaler()
    ms.setMarkerFileName(os.fspath(f["static"]))
    ms.setOutputModelFileName(os.fspath(ref / "scaled_only.osim"))
    ms.setOutputScaleFileName(os.fspath(ref / "scale_set.xml"))
    mp = tool.getMarkerPlacer()
    mp.setMarkerFileName(os.fspath(f["static"]))
    mp.setOutputModelFileName(os.fspath(ref / "scaled.osim"))
    mp.setOutputMotionFileName(os.fspath(ref / "static_pose.mot"))
    assert tool.run()
    return ours, ref, f


def _static_mean(opensim, trc, t0, t1):
    """Marker -> mean position (m) over [t0, t1] of a TRC in mm, read with the opensim API."""
    tab = opensim.TimeSeriesTableVec3(os.fspath(trc))
    time = np.array(tab.getIndependentColumn())
    rows = np.flatnonzero((time >= t0 - 1e-9) & (time <= t1 + 1e-9))
    out = {}
    for j, name in enumerate(tab.getColumnLabels()):
        col = tab.getDependentColumnAtIndex(j)
        out[name] = 1e-3 * np.mean([[col[int(r)].get(k) for k in range(3)] for r in rows], axis=0)
    return out


def _pose_errors(opensim, model_path, mot, mean, markers):
    """|marker in ground - static mean| (m) of `markers` with `model_path` posed at the single row of `mot`."""
    om = opensim.Model(os.fspath(model_path))
    s = om.initSystem()
    sto = opensim.Storage(os.fspath(mot))
    arr = sto.getColumnLabels()
    labels = [arr.get(i) for i in range(arr.getSize())]
    row = sto.getStateVector(0).getData()
    cs = om.getCoordinateSet()
    deg = sto.isInDegrees()
    for i in range(cs.getSize()):
        c = cs.get(i)
        name = next((lab for lab in labels if lab in (c.getName(), f"{c.getAbsolutePathString()}/value")), None)
        assert name is not None, c.getName()
        v = row.get(labels.index(name) - 1)
        if deg and int(c.getMotionType()) == 1:
            v = np.radians(v)
        c.setValue(s, float(v), False)
    om.realizePosition(s)
    mset = om.getMarkerSet()
    return {m: float(np.linalg.norm(np.array(mset.get(m).getLocationInGround(s).to_numpy()) - mean[m]))
            for m in markers}


def test_scale_factors_within_2_percent_of_scaletool(scale_runs, opensim):
    ours, ref, _ = scale_runs
    report = json.loads((ours / "scale.json").read_text())
    mine = report["scale_factors"]
    theirs = {}
    ss = opensim.ScaleSet(os.fspath(ref / "scale_set.xml"))
    for i in range(ss.getSize()):
        sc = ss.get(i)
        theirs[sc.getSegmentName()] = np.array(sc.getScaleFactors().to_numpy())
    assert set(mine) <= set(theirs)
    scaled = [b for b in theirs if not np.allclose(theirs[b], 1.0)]
    assert len(scaled) >= 10                      # ScaleTool did scale the legs, pelvis and torso
    for body, f in mine.items():
        np.testing.assert_allclose(f, theirs[body], rtol=0.02, err_msg=body)
    assert report["mass_kg"]["scaled"] == pytest.approx(72.6, abs=1e-6)      # the setup's subject mass


def test_marker_rms_within_1mm_of_scaletool(scale_runs, opensim):
    ours, ref, f = scale_runs
    report = json.loads((ours / "scale.json").read_text())
    place = report["marker_placement"]
    t0, t1 = place["time_range_s"]
    mean = _static_mean(opensim, f["static"], t0, t1)
    markers = list(place["per_marker_m"])
    assert len(markers) >= 35
    # ScaleTool's static-pose IK error: its scaled model before placement, at the pose its MarkerPlacer solved
    e_ref = _pose_errors(opensim, ref / "scaled_only.osim", ref / "static_pose.mot", mean, markers)
    rms_ref = np.sqrt(np.mean(np.square(list(e_ref.values()))))
    assert abs(place["rms_m"] - rms_ref) < 1e-3, (place["rms_m"], rms_ref)
    assert abs(place["max_m"] - max(e_ref.values())) < 5e-3
    # the placed markers sit on the static's mean positions at our pose (the placement itself, with our model file)
    e_ours = _pose_errors(opensim, ours / "scaled_model.osim", ours / "static_pose.mot", mean, place["moved_markers"])
    assert max(e_ours.values()) < 1e-6
    # and our scaled model is the same size as ScaleTool's: markers in their body frames before placement agree
    ours_model = opensim.Model(os.fspath(ours / "scaled_model.osim"))
    ref_model = opensim.Model(os.fspath(ref / "scaled.osim"))
    d = [np.linalg.norm(np.array(ours_model.getMarkerSet().get(m).get_location().to_numpy())
                        - np.array(ref_model.getMarkerSet().get(m).get_location().to_numpy())) for m in markers]
    assert np.median(d) < 5e-3


def test_scale_bad_inputs_one_line_exit_2_no_output(shared_data, opensim, tmp_path, capsys):
    from kinematics.io.storage import read_trc, write_trc

    f = _files(shared_data)
    trial = read_trc(f["static"])
    lacking = tmp_path / "static_no_head.trc"
    write_trc(lacking, trial.subset([n for n in trial.names if n != "Top.Head"]), units="mm")
    base = ["--model", str(f["model"]), "--setup", str(f["setup"]), "--marker-set", str(f["marker_set"])]
    text = f["setup"].read_text(encoding="utf-8")
    assert "V.Sacral Top.Head" in text
    odd_setup = tmp_path / "setup_top_hat.xml"          # a pair naming a marker neither model nor marker set has
    odd_setup.write_text(text.replace("V.Sacral Top.Head", "V.Sacral Top.Hat"), encoding="utf-8")
    cases = [
        ([str(lacking), *base], ["static_no_head.trc", "Top.Head", "torso"]),
        ([str(tmp_path / "absent.c3d"), *base], ["absent.c3d", "not found"]),
        ([str(f["static"]), "--model", str(tmp_path / "none.osim"), "--setup", str(f["setup"])], ["none.osim"]),
        ([str(f["static"]), *base[:4], "--marker-set", "pig"], ["pig", "MarkerSet"]),
        ([str(f["static"]), "--model", str(f["model"]), "--setup", str(odd_setup), "--marker-set", str(f["marker_set"])],
         ["gait2392_Scale_MarkerSet.xml", "Top.Hat", "not in the model's marker set"]),
    ]
    for k, (args, words) in enumerate(cases):
        out = tmp_path / f"out{k}"
        assert main(["scale", *args, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and "\n" not in err and "Traceback" not in err, err
        for w in words:
            assert w in err, (w, err)
        assert not out.exists()
        assert not list(tmp_path.glob(f".out{k}*"))          # no staging folder left behind


def test_scale_from_a_z_up_lab_facing_minus_y(scale_runs, tmp_path):
    """The same static recorded in a Z-up lab, the subject facing -Y: the same model (lab read from the markers)."""
    from dataclasses import replace

    from kinematics.io.storage import read_trc, write_trc
    from personalize.scaling import scale_model

    ours, _, f = scale_runs
    trial = read_trc(f["static"])
    # OpenSim ground (X facing, Y up, Z right) -> lab (a rotation): X_lab = -Z, Y_lab = -X, Z_lab = Y (facing -Y, Z up)
    lab_from_ground = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert np.linalg.det(lab_from_ground) == pytest.approx(1.0)
    zup = tmp_path / "static_zup.trc"
    write_trc(zup, replace(trial, positions=trial.positions @ lab_from_ground.T), units="mm")
    res = scale_model(zup, f["model"], setup=f["setup"], marker_set=f["marker_set"])
    assert res.lab.up_axis == "+Z"
    report = json.loads((ours / "scale.json").read_text())
    for body, fac in report["scale_factors"].items():
        np.testing.assert_allclose(res.scale_factors[body], fac, rtol=1e-9, err_msg=body)
    assert res.marker_rms == pytest.approx(report["marker_placement"]["rms_m"], abs=1e-6)
