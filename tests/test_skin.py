"""`personalize.skin`: soft tissue under the pelvic markers measured in the body/skin label; the phantoms' skin."""
from __future__ import annotations

import json

import numpy as np
import pytest

from lowerlimb.errors import InputError
from personalize.io import LabelVolume, read_label_map, read_label_volume, read_tissue_label
from personalize.skin import MAX_THICKNESS, POSTURE_SD, measure_skin_thickness
from phantoms import make_phantom
from phantoms.imaging import SkinField, label_volume, write_label_nifti
from lowerlimb.geometry import DEFAULT_MARKER_RADIUS
from phantoms.skeleton import pelvis_skin_sites, phantom_skeleton

MM = np.diag([1e-3, 1e-3, 1e-3, 1.0])


@pytest.fixture(scope="module", params=[3, 11, 1003])
def pelvis_with_skin(request):
    """Pelvis-only 2 mm label volume with the skin envelope (seed 11: a PSIS whose ray grazes the skin;
    seed 1003: ASIS 1.8 mm, PSIS 24 mm)."""
    seed = request.param
    ph = make_phantom(seed=seed)
    labels, aff, lmap = label_volume(ph, voxel=(2e-3,) * 3, seed=seed, bones=["pelvis"], skin=True)
    return seed, ph, LabelVolume(labels, MM @ aff, {"pelvis": lmap["pelvis"]}, "phantom", tissue_label=lmap["skin"])


def test_skin_passes_at_the_drawn_thickness(pelvis_with_skin):
    """The continuous envelope crosses each marker ray first at the skeleton's tissue, and the markers sit on it."""
    seed, ph, _ = pelvis_with_skin
    field = SkinField.of(ph, seed)
    sk = phantom_skeleton(ph, seed)
    for name, (p, n, t) in field.sites.items():
        assert t == pytest.approx(sk.tissue_thickness[name[1:]], abs=1e-12)
        assert field.crossing(ph, name) == pytest.approx(t, abs=1e-5)
    # the skeleton's marker = landmark + (t + r) n in the skeleton's frame: same distance from the landmark
    plm = ph.body_truth()["bones"]["pelvis"]["landmarks"]
    site = sk.sites["RPSI"]
    assert site.body == "pelvis"
    d_marker = np.linalg.norm(site.offset - sk.sites["RASI"].offset)
    p_r, n_r, t_r = field.sites["RPSI"]
    p_a, n_a, t_a = field.sites["RASI"]
    r = DEFAULT_MARKER_RADIUS
    assert d_marker == pytest.approx(np.linalg.norm((p_r + (t_r + r) * n_r) - (p_a + (t_a + r) * n_a)), abs=1e-9)
    assert np.linalg.norm(np.asarray(plm["RASI"])) > 0


def test_measured_thickness_matches_truth_within_its_sd(pelvis_with_skin):
    seed, ph, vol = pelvis_with_skin
    sites = pelvis_skin_sites(ph, seed)
    res = measure_skin_thickness(vol, {k: (v[0], None) for k, v in sites.items()}, {k: v[1] for k, v in sites.items()})
    for k, (p, n, t) in sites.items():
        r = res[k]
        assert r.source == "MRI" and r.note == ""
        err = abs(r.thickness - t)
        assert err <= r.sd, (seed, k, r.thickness, t, r.sd)
        # much tighter than the stated sd: a fraction of the 2 mm voxel (the sd holds the assumed posture term)
        assert err < 1.2e-3, (seed, k, err)
        assert r.sd >= POSTURE_SD and r.components["voxel"] == pytest.approx(2e-3 / np.sqrt(12), rel=0.8)
        assert np.linalg.norm(r.exit_point - (p + r.thickness * n)) < 1e-9


def _slab(thickness_mm: float, depth_mm: int = 120, h=1.0):
    """Analytic volume (1 mm voxels): bone z < 0 (label 1), body 0 <= z <= thickness (label 16) by voxel centres."""
    nz = depth_mm + 40
    lab = np.zeros((30, 30, nz), np.int16)
    z = (np.arange(nz) - 40 + 0.5) * h          # voxel centres, mm; bone surface at z = 0
    lab[:, :, z < 0] = 1
    lab[:, :, (z >= 0) & (z <= thickness_mm)] = 16
    A = np.eye(4)
    A[2, 3] = (-40.0 + 0.5) * h                 # voxel k centre at z = k - 39.5 mm
    return LabelVolume(lab, MM @ A, {"pelvis": 1}, "slab", tissue_label=16)


def test_analytic_slab_and_implausible_values():
    p = np.array([0.0145, 0.0145, 0.0])
    n = np.array([0.0, 0.0, 1.0])
    for t_mm in (5.2, 25.2, 61.7):
        r = measure_skin_thickness(_slab(t_mm), {"RPSI": (p, np.diag([1e-6, 1e-6, 4e-6]))}, {"RPSI": n})["RPSI"]
        assert r.source == "MRI"
        assert abs(r.thickness - t_mm * 1e-3) <= 0.5e-3          # the half-voxel quantisation bound
        assert r.components["landmark"] == pytest.approx(2e-3)   # n^T C n
        # a flat skin: tilting the ray by the normal's 10 deg sd lengthens it by t (1/cos - 1), per tangent axis
        expected = np.sqrt(2) * t_mm * 1e-3 * (1 / np.cos(np.radians(10)) - 1)
        assert abs(r.components["normal"] - expected) < 0.5e-3
    # thicker than the plausible maximum -> prior + low confidence
    r = measure_skin_thickness(_slab(90.0), {"RPSI": (p, None)}, {"RPSI": n})["RPSI"]
    assert MAX_THICKNESS < 0.09
    assert r.source == "prior" and "low confidence" in r.note and r.thickness == pytest.approx(0.0196)
    # body beyond the ray's 100 mm, and body up to the image border (50 mm): never leaves the body
    r = measure_skin_thickness(_slab(200.0), {"LPSI": (p, None)}, {"LPSI": n})["LPSI"]
    assert r.source == "prior" and "low confidence" in r.note and "never leaves the body" in r.note
    r = measure_skin_thickness(_slab(200.0, depth_mm=50), {"LPSI": (p, None)}, {"LPSI": n})["LPSI"]
    assert r.source == "prior" and "low confidence" in r.note and "leaves the image" in r.note
    # a landmark outside the body label (pointing the wrong way)
    r = measure_skin_thickness(_slab(10.0), {"RASI": (p + [0, 0, 0.05], None)}, {"RASI": n})["RASI"]
    assert r.source == "prior" and "not inside the body" in r.note and r.thickness == pytest.approx(0.0097)


def test_bone_only_volume_keeps_the_prior():
    vol = _slab(20.0)
    vol = LabelVolume(vol.labels, vol.affine_m, vol.label_map, "bones only")     # no tissue label
    r = measure_skin_thickness(vol, {"RASI": (np.zeros(3), None)}, {"RASI": np.array([0, 0, 1.0])})["RASI"]
    assert (r.source, r.thickness, r.sd) == ("prior", pytest.approx(0.0097), pytest.approx(0.0070))


def test_label_map_skin_entry_and_aliases(tmp_path):
    lab = _slab(20.0).labels
    write_label_nifti(tmp_path / "labels.nii.gz", lab, np.eye(4))
    for key in ("skin", "body", "soft_tissue"):
        (tmp_path / "label_map.json").write_text(json.dumps({"pelvis": 1, key: 16}))
        assert read_label_map(tmp_path / "label_map.json")[0] == {"pelvis": 1}
        assert read_tissue_label(tmp_path / "label_map.json") == 16
        vol = read_label_volume(tmp_path / "labels.nii.gz")
        assert vol.tissue_label == 16 and vol.label_map == {"pelvis": 1}
    (tmp_path / "label_map.json").write_text(json.dumps({"pelvis": 1}))
    assert read_label_volume(tmp_path / "labels.nii.gz").tissue_label is None
    assert read_tissue_label(None) is None
    with pytest.raises(InputError, match="skin and for a bone"):
        read_label_map({"pelvis": 1, "skin": 1})
    with pytest.raises(InputError, match="appears 2 times"):
        read_label_map({"pelvis": 1, "skin": 16, "body": 17})


def test_skin_label_leaves_the_bones_untouched(tmp_path):
    """Bones are labelled over the body: the same bone voxels with and without the skin (on the shared lattice),
    the skin label only outside the bones, and the written folder names it in label_map.json and truth.json."""
    from phantoms.imaging import write_phantom

    ph = make_phantom(seed=7)
    a, aff_a, lm_a = label_volume(ph, voxel=(3e-3,) * 3, seed=7, bones=["pelvis", "femur_r"])
    b, aff_b, lm_b = label_volume(ph, voxel=(3e-3,) * 3, seed=7, bones=["pelvis", "femur_r"], skin=True)
    assert "skin" not in lm_a and lm_b["skin"] not in lm_a.values()
    off = np.round((aff_a[:3, 3] - aff_b[:3, 3]) / 3.0).astype(int)
    assert np.all(off >= 0) and np.all(np.array(b.shape) >= np.array(a.shape) + off)
    sub = b[off[0]:off[0] + a.shape[0], off[1]:off[1] + a.shape[1], off[2]:off[2] + a.shape[2]]
    bones_b = np.where(sub == lm_b["skin"], 0, sub)
    np.testing.assert_array_equal(bones_b, a)
    assert (b == lm_b["skin"]).sum() > 1000
    write_phantom(tmp_path, ph, voxel=(3e-3,) * 3, seed=7, bones=["pelvis"], meshes=False)
    lm = json.loads((tmp_path / "label_map.json").read_text())
    assert read_tissue_label(tmp_path / "label_map.json") == lm["skin"]
    sites = json.loads((tmp_path / "truth.json").read_text())["image"]["skin"]["sites"]
    assert set(sites) == {"RASI", "LASI", "RPSI", "LPSI"}
    assert sites["RPSI"]["thickness"] == pytest.approx(phantom_skeleton(ph, 7).tissue_thickness["PSI"])
