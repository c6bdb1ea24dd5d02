"""``personalize bones``: output contract on a phantom label volume, and bad input (exit 2 or flags, never a crash)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from personalize.cli import main


@pytest.fixture(scope="module")
def phantom_volume(tmp_path_factory):
    from phantoms.anatomy import make_phantom
    from phantoms.imaging import label_volume, write_label_nifti

    ph = make_phantom(seed=5)
    labels, affine_mm, _ = label_volume(ph, voxel=(1e-3,) * 3, bones=["femur_r", "tibia_r", "fibula_r"])
    d = tmp_path_factory.mktemp("bones_cli")
    path = write_label_nifti(d / "labels.nii.gz", labels, affine_mm)
    return path, ph.truth()


@pytest.fixture(scope="module")
def cli_output(phantom_volume, tmp_path_factory):
    path, truth = phantom_volume
    out = tmp_path_factory.mktemp("bones_out") / "result"
    code = main(["bones", str(path), "--out", str(out), "--quiet"])
    return code, out, truth


def test_writes_the_output_contract(cli_output):
    code, out, truth = cli_output
    assert code == 0
    for f in ("landmarks.json", "joints.json", "fits.json", "femur_r.png", "tibia_r.png"):
        assert (out / f).is_file(), f
    lm = json.loads((out / "landmarks.json").read_text())
    assert lm["units"] == "m" and lm["frame"] == "input"
    fem = lm["bones"]["femur_r"]
    for name in ("femoral_head_centre", "RKNE", "RMFC", "RTRO", "intercondylar_midpoint"):
        entry = fem["landmarks"][name]
        assert len(entry["position"]) == 3 and np.asarray(entry["cov"]).shape == (3, 3)
    assert set(fem["axes"]["knee_axis"]) == {"point", "direction", "sd_deg"}
    assert {"RTTB", "RMMA"} <= set(lm["bones"]["tibia_r"]["landmarks"])
    assert {"RHFB", "RANK"} <= set(lm["bones"]["fibula_r"]["landmarks"])
    j = json.loads((out / "joints.json").read_text())
    assert j["units"] == "m" and j["frame"] == "input"
    knee = j["joints"]["knee_r"]
    R = np.asarray(knee["rotation"])
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
    # compared key by key with the phantom truth (same schema)
    t = truth["joints"]["joints"]["knee_r"]
    assert np.linalg.norm(np.asarray(knee["origin"]) - np.asarray(t["origin"])) < 1e-3
    za = np.asarray(t["rotation"])[:, 2]
    assert np.degrees(np.arccos(np.clip(R[:, 2] @ za, -1, 1))) < 1.0
    assert "ankle_r" in j["dropped"] and "talus_r" in j["dropped"]["ankle_r"]
    fits = json.loads((out / "fits.json").read_text())
    assert fits["bones"]["femur_r"]["femoral_head"]["type"] == "sphere"


def _write_ply(path: Path, mesh: trimesh.Trimesh, scale=1000.0):
    m = mesh.copy()
    m.apply_scale(scale)
    m.export(path)


def test_folder_without_bones_exits_2(tmp_path, capsys):
    d = tmp_path / "meshes"
    d.mkdir()
    (d / "notes.txt").write_text("nothing here")
    _write_ply(d / "kidney.ply", trimesh.creation.icosphere(radius=0.03))
    code = main(["bones", str(d), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.strip().startswith("error:") and "Traceback" not in err
    assert not (tmp_path / "out" / "landmarks.json").exists()


def test_missing_input_exits_2(tmp_path, capsys):
    code = main(["bones", str(tmp_path / "nope"), "--out", str(tmp_path / "out")])
    assert code == 2
    assert "error:" in capsys.readouterr().err


def test_open_surface_never_crashes(tmp_path, capsys):
    d = tmp_path / "meshes"
    d.mkdir()
    # a long open tube (no caps): not a closed bone surface
    tube = trimesh.creation.cylinder(radius=0.015, height=0.4, sections=48)
    keep = np.abs(tube.face_normals[:, 2]) < 0.5
    open_tube = trimesh.Trimesh(tube.vertices, tube.faces[keep], process=True)
    _write_ply(d / "femur_r.ply", open_tube)
    out = tmp_path / "out"
    code = main(["bones", str(d), "--out", str(out), "--no-png", "--quiet"])
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error" not in err
    if code == 0:
        fem = json.loads((out / "landmarks.json").read_text())["bones"]["femur_r"]
        assert "low_confidence" in fem["flags"]
    else:
        assert code == 2 and err.strip().startswith("error:")


def test_tibia_named_femur_is_flagged(tmp_path, capsys):
    from phantoms.anatomy import make_phantom
    from phantoms.imaging import label_volume
    from personalize.io import LabelVolume
    from personalize.surfaces import surfaces_from_labels

    ph = make_phantom(seed=6)
    labels, aff, lmap = label_volume(ph, voxel=(1e-3,) * 3, bones=["tibia_r"])
    vol = LabelVolume(labels=labels, affine_m=np.diag([1e-3, 1e-3, 1e-3, 1.0]) @ aff, label_map=lmap, source="t")
    tibia = surfaces_from_labels(vol, workers=1)["tibia_r"].mesh
    d = tmp_path / "meshes"
    d.mkdir()
    _write_ply(d / "femur_r.ply", tibia)
    out = tmp_path / "out"
    capsys.readouterr()
    # refused by default (one line naming the file), used as named and flagged with --trust-names
    assert main(["bones", str(d), "--out", str(out), "--no-png", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "femur_r.ply" in err and "--trust-names" in err
    assert not out.exists()
    code = main(["bones", str(d), "--out", str(out), "--no-png", "--quiet", "--trust-names"])
    assert code == 0, capsys.readouterr().err
    fem = json.loads((out / "landmarks.json").read_text())["bones"]["femur_r"]
    assert "name_mismatch" in fem["flags"] and "low_confidence" in fem["flags"]


def test_scalars_follow_the_truth_schema(cli_output):
    code, out, truth = cli_output
    lm = json.loads((out / "landmarks.json").read_text())
    mine = lm["bones"]["femur_r"]["scalars"]["femoral_head_radius"]
    ref = truth["landmarks"]["bones"]["femur_r"]["scalars"]["femoral_head_radius"]
    assert set(mine) == set(ref) == {"value", "sd"}
    assert abs(mine["value"] - ref["value"]) < 3e-4 and 0 < mine["sd"] < 1e-3
