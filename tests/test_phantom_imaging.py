"""Phantom imaging: label volumes (partial volume, anisotropy, noise, FOV), writers and the CLI."""
from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest
import trimesh
from scipy import ndimage

from lowerlimb.errors import InputError
from lowerlimb.bones import DEFAULT_LABEL_MAP
from personalize.cli import main
from phantoms import make_phantom
from phantoms.imaging import label_volume, write_phantom


@pytest.fixture(scope="module")
def ph():
    return make_phantom(seed=7)


@pytest.fixture(scope="module")
def femur_labels(ph):
    return label_volume(ph, voxel=(1e-3, 1e-3, 1e-3), bones=["femur_r", "pelvis"])


def _world_mm(affine, idx):
    return np.c_[idx, np.ones(len(idx))] @ affine.T


def test_femur_volume_matches_mesh_at_1mm(ph, femur_labels):
    labels, affine, lm = femur_labels
    assert labels.dtype == np.int16
    assert lm == {"femur_r": DEFAULT_LABEL_MAP["femur_r"], "pelvis": DEFAULT_LABEL_MAP["pelvis"]}
    vox_mm3 = abs(np.linalg.det(affine[:3, :3]))
    assert vox_mm3 == pytest.approx(1.0)
    v_f = np.count_nonzero(labels == lm["femur_r"]) * vox_mm3 * 1e-9
    assert abs(v_f / ph.mesh("femur_r").volume - 1) < 0.01


def test_affine_maps_voxels_to_scanner_mm(ph, femur_labels):
    labels, affine, lm = femur_labels
    # voxel centres labelled femur are inside (or within half a voxel diagonal of) the femur
    idx = np.column_stack(np.nonzero(labels == lm["femur_r"]))[::97]
    pts = _world_mm(affine, idx)[:, :3] / 1000.0
    assert ph.sdf("femur_r", pts).max() < 0.5 * np.sqrt(3) * 1e-3
    # and the femoral head centre falls in a femur voxel
    t = ph.truth()["landmarks"]["bones"]["femur_r"]["landmarks"]["femoral_head_centre"]["position"]
    ijk = np.round(np.linalg.solve(affine, np.r_[np.array(t) * 1000.0, 1.0])[:3]).astype(int)
    assert labels[tuple(ijk)] == lm["femur_r"]
    # the acetabular cartilage gap stays background between head and cup
    assert np.count_nonzero(labels == lm["pelvis"]) > 100_000


def test_anisotropic_spacing(ph):
    labels, affine, lm = label_volume(ph, voxel=(0.5e-3, 0.5e-3, 2e-3), bones=["talus_r"])
    np.testing.assert_allclose(np.diag(affine)[:3], [0.5, 0.5, 2.0])
    v = np.count_nonzero(labels == lm["talus_r"]) * 0.5e-9
    assert abs(v / ph.mesh("talus_r").volume - 1) < 0.02
    # partial-volume rule: voxels labelled with the centre outside the bone exist only by >= 50 % coverage
    idx = np.column_stack(np.nonzero(labels == lm["talus_r"]))
    d = ph.sdf("talus_r", _world_mm(affine, idx)[:, :3] / 1000.0)
    assert d.max() < 1e-3


def test_noise_is_seeded_and_plausible(ph):
    clean, _, lm = label_volume(ph, bones=["talus_r"])
    a, _, _ = label_volume(ph, bones=["talus_r"], noise=0.8, seed=1)
    b, _, _ = label_volume(ph, bones=["talus_r"], noise=0.8, seed=1)
    c, _, _ = label_volume(ph, bones=["talus_r"], noise=0.8, seed=2)
    np.testing.assert_array_equal(a, b)
    assert np.count_nonzero(a != c) > 100
    lab = lm["talus_r"]
    changed = np.count_nonzero((a == lab) != (clean == lab))
    assert changed > 300                                  # boundary jitter, holes, islands
    assert abs(np.count_nonzero(a == lab) / np.count_nonzero(clean == lab) - 1) < 0.05
    n_clean = ndimage.label(clean == lab)[1]
    n_noisy = ndimage.label(a == lab)[1]
    assert n_noisy > n_clean                               # spurious islands
    holes = ndimage.binary_fill_holes(a == lab) & (a != lab)
    assert np.count_nonzero(holes) > 0                     # small internal holes


def test_truncated_field_of_view(ph):
    full, aff_f, lm = label_volume(ph, bones=["femur_r"])
    half, aff_h, _ = label_volume(ph, bones=["femur_r"], fov=("femur_r", 0.5, 1.0))
    frac = np.count_nonzero(half) / np.count_nonzero(full)
    assert 0.3 < frac < 0.7
    # the same voxel grid: truncated volume is a sub-block of the full one
    off = np.round(np.linalg.solve(aff_f, aff_h[:, 3])[:3]).astype(int)
    sub = full[off[0]:off[0] + half.shape[0], off[1]:off[1] + half.shape[1], off[2]:off[2] + half.shape[2]]
    np.testing.assert_array_equal(sub, half)
    lo = aff_f[:3, 3] / 1000.0 + 0.03
    box, aff_b, _ = label_volume(ph, bones=["femur_r"], fov=np.array([lo, lo + 0.05]))
    assert max(box.shape) <= 52
    with pytest.raises(InputError, match="fov"):
        label_volume(ph, bones=["femur_r"], fov=np.array([lo + 5, lo + 6]))


def test_overlap_goes_to_the_nearest_surface():
    ph = make_phantom(seed=0, placement="identity")
    labels, affine, lm = label_volume(ph, bones=["tibia_r", "fibula_r"], voxel=(1e-3, 1e-3, 1e-3))
    idx = np.column_stack(np.nonzero(labels > 0))[::13]
    pts = _world_mm(affine, idx)[:, :3] / 1000.0
    dt, df = ph.sdf("tibia_r", pts), ph.sdf("fibula_r", pts)
    both = (dt < 0) & (df < 0)
    got = labels[tuple(idx.T)]
    want = np.where(dt < df, lm["tibia_r"], lm["fibula_r"])
    np.testing.assert_array_equal(got[both], want[both])


def test_bad_inputs(ph):
    with pytest.raises(InputError, match="voxel"):
        label_volume(ph, voxel=(1.0, 1.0, 1.0))           # millimetres given as metres
    with pytest.raises(InputError, match="noise"):
        label_volume(ph, noise=3)
    with pytest.raises(InputError, match="bones"):
        label_volume(ph, bones=["femur_x"])


def test_write_phantom_files(tmp_path, ph):
    paths = write_phantom(tmp_path, ph, voxel=(1e-3, 1e-3, 1.5e-3), bones=["patella_r", "talus_r"])
    img = nib.load(tmp_path / "labels.nii.gz")
    assert img.header.get_xyzt_units()[0] == "mm"
    np.testing.assert_allclose(np.diag(img.affine)[:3], [1.0, 1.0, 1.5])
    lm = json.loads((tmp_path / "label_map.json").read_text())
    assert lm == {"patella_r": DEFAULT_LABEL_MAP["patella_r"], "talus_r": DEFAULT_LABEL_MAP["talus_r"]}
    data = np.asarray(img.dataobj)
    assert set(np.unique(data)) == {0, *lm.values()}
    mesh = trimesh.load(tmp_path / "meshes" / "talus_r.ply")
    np.testing.assert_allclose(mesh.vertices / 1000.0, ph.mesh("talus_r").vertices, atol=1e-7)
    head = (tmp_path / "meshes" / "talus_r.ply").read_bytes()[:400].decode("ascii", "replace")
    assert "comment units mm" in head and "frame scanner" in head
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert truth["units"] == "m" and truth["frame"] == "scanner"
    np.testing.assert_allclose(truth["joints"]["joints"]["ankle_r"]["origin"],
                               ph.truth()["joints"]["joints"]["ankle_r"]["origin"])
    assert set(paths) >= {"labels", "label_map", "truth", "mesh:talus_r"}


def test_cli_phantom(tmp_path, capsys):
    out = tmp_path / "ph"
    code = main(["phantom", "--out", str(out), "--seed", "2", "--side", "r", "--voxel", "1", "1", "2",
                 "--noise", "low", "--bones", "patella_r,talus_r", "--no-motion"])
    assert code == 0
    assert "wrote phantom" in capsys.readouterr().out
    assert {p.name for p in out.iterdir()} == {"labels.nii.gz", "label_map.json", "meshes", "truth.json"}
    truth = json.loads((out / "truth.json").read_text())
    assert truth["params"]["seed"] == 2
    assert "femur_l" not in truth["landmarks"]["bones"]
    np.testing.assert_allclose(np.diag(nib.load(out / "labels.nii.gz").affine)[:3], [1, 1, 2])
    for bad in (["--noise", "loud"], ["--side", "both-ish"], ["--voxel", "0", "1", "1"], ["--bones", "femur_x"],
                ["--side", "r"]):
        code = main(["phantom", "--out", str(tmp_path / "bad"), *bad])
        err = capsys.readouterr().err
        assert code == 2 and err.startswith("error: ") and len(err.strip().splitlines()) == 1, (bad, err)
        assert not (tmp_path / "bad").exists()


def test_cli_child_phantom_with_open_growth_plates(tmp_path, capsys):
    """A child's label volume from the CLI: the femoral head is a separate piece, and
    ``personalize bones`` joins it back and finds the hip centre."""
    import scipy.ndimage as ndi

    out = tmp_path / "child"
    assert main(["phantom", "--out", str(out), "--seed", "1", "--side", "r", "--stature", "1.2",
                 "--growth-plates", "1.5", "--bones", "femur_r", "--no-motion"]) == 0
    truth = json.loads((out / "truth.json").read_text())
    assert truth["image"]["growth_plates_m"] == pytest.approx(1.5e-3)
    labels = np.asarray(nib.load(out / "labels.nii.gz").dataobj)
    assert ndi.label(labels > 0, structure=np.ones((3, 3, 3), bool))[1] == 3   # shaft + head + distal epiphysis
    res = tmp_path / "bones"
    assert main(["bones", str(out / "labels.nii.gz"), "--label-map", str(out / "label_map.json"),
                 "--out", str(res), "--quiet", "--no-png"]) == 0
    lm = json.loads((res / "landmarks.json").read_text())["bones"]["femur_r"]
    head = np.asarray(lm["landmarks"]["femoral_head_centre"]["position"])
    true_head = np.asarray(truth["landmarks"]["bones"]["femur_r"]["landmarks"]["femoral_head_centre"]["position"])
    assert np.linalg.norm(head - true_head) < 0.5e-3
    assert not lm["flags"]
    code = main(["phantom", "--out", str(tmp_path / "bad"), "--growth-plates", "20", "--no-motion", "--side", "r"])
    assert code == 2 and "--growth-plates" in capsys.readouterr().err


def test_cli_phantom_writes_a_subject_with_motion(tmp_path):
    """The default phantom folder is a subject: trials, truth coordinates and the knee laws in truth.json."""
    from kinematics.io.c3d import read_c3d
    from kinematics.mechanisms.correlative import CorrelativeLaw
    from kinematics.io.storage import read_mot

    out = tmp_path / "subject"
    assert main(["phantom", "--out", str(out), "--seed", "4", "--bones", "patella_r"]) == 0
    names = {p.name for p in out.iterdir()}
    assert {"static.c3d", "gait_01.c3d", "functional_hip.c3d", "subject.json", "truth", "truth.json"} <= names
    assert any(n.startswith("crouch_090_") for n in names)
    truth = json.loads((out / "truth.json").read_text())
    law = CorrelativeLaw.from_json(truth["knee_law_r"])
    mot = read_mot(out / "truth" / "gait_01.mot")
    rot = mot.to_radians(["knee_flexion_r", "knee_adduction_r", "knee_rotation_r"])
    angles = np.column_stack([rot.column(c) for c in ("knee_flexion_r", "knee_adduction_r", "knee_rotation_r")])
    trans = np.column_stack([mot.column(c) for c in ("knee_tx_r", "knee_ty_r", "knee_tz_r")])
    np.testing.assert_allclose(law.predict(angles), trans, atol=1e-6)
    static = read_c3d(out / "static.c3d")
    assert {"RASI", "LASI", "RKNE", "RANK", "RHEE"} <= set(static.names)
    assert truth["params"]["seed"] == 4 and "femur_r" in truth["landmarks"]["bones"]
