"""Landmarks and joints on phantom label volumes: accuracy, rigid-motion equivariance, mirror symmetry, truncation.

The phantom's bones are rasterised (1 mm isotropic; 0.5 x 0.5 x 2 mm with
segmentation noise), surfaced by `personalize.surfaces` and detected; errors
are measured against ``truth.json`` (`personalize.landmarks.evaluate`).  The
issue's tolerances are 95th percentiles over 10 seeds; the suite runs a few
seeds and asserts every one of them (stricter per case), the benchmark
``benchmarks/landmarks.py --phantom`` runs all 10.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from personalize.frames import joints_from_landmarks
from personalize.landmarks import detect_landmarks
from personalize.landmarks.evaluate import TOLERANCES, phantom_case

ISO_SEEDS = (0, 1)


@pytest.fixture(scope="module")
def iso_cases():
    bones = ("femur", "tibia", "fibula", "talus", "calcn", "toes", "patella")
    return {s: phantom_case(s, voxel=(1e-3, 1e-3, 1e-3), noise=0.0, bones=bones) for s in ISO_SEEDS}


@pytest.fixture(scope="module")
def aniso_case():
    return phantom_case(2, voxel=(0.5e-3, 0.5e-3, 2e-3), noise=0.5)


@pytest.mark.parametrize("seed", ISO_SEEDS)
@pytest.mark.parametrize("metric", ["hip_centre", "knee_centre", "knee_axis", "ankle_centre", "ankle_axis",
                                    "ground_contacts"])
def test_iso_1mm_accuracy(iso_cases, seed, metric):
    err = iso_cases[seed]["errors"][metric]
    assert err <= TOLERANCES[metric], f"seed {seed}: {metric} error {err:.3f} > {TOLERANCES[metric]}"


@pytest.mark.parametrize("metric", ["hip_centre", "knee_centre", "knee_axis", "ankle_centre", "ground_contacts"])
def test_aniso_noisy_accuracy(aniso_case, metric):
    err = aniso_case["errors"][metric]
    assert err <= 2 * TOLERANCES[metric], f"{metric} error {err:.3f} > {2 * TOLERANCES[metric]}"


# --------------------------------------------------------------------------- subtalar axis
# The phantom's talus carries the Parr et al. 2012 geometry exactly (convex
# talar head sphere, concave posterior-facet sphere, axis through both centres).
@pytest.mark.parametrize("seed", ISO_SEEDS)
def test_subtalar_axis_iso_1mm(iso_cases, seed):
    err = iso_cases[seed]["errors"]["subtalar_axis"]
    assert err <= TOLERANCES["subtalar_axis"], f"seed {seed}: subtalar axis error {err:.2f} deg"
    # the two sphere centres themselves: the head is well sampled, the facet is a shallow cap
    from phantoms.anatomy import make_phantom

    truth = make_phantom(seed=seed).truth()["landmarks"]["bones"]["talus_r"]["landmarks"]
    tal = iso_cases[seed]["landmarks"].bones["talus_r"]
    for name, tol in (("talar_head_centre", 1e-3), ("posterior_facet_centre", 3e-3)):
        e = np.linalg.norm(tal.landmarks[name].position - np.asarray(truth[name]["position"]))
        assert e < tol, f"seed {seed}: {name} off by {e * 1e3:.2f} mm"


def test_subtalar_axis_aniso_noisy(aniso_case):
    err = aniso_case["errors"]["subtalar_axis"]
    assert err <= 2 * TOLERANCES["subtalar_axis"], f"subtalar axis error {err:.2f} deg"
    assert 0 < aniso_case["joints"]["subtalar_r"].axis_sd_deg < 10


def test_sides_and_no_spurious_flags(iso_cases):
    ls = iso_cases[0]["landmarks"]
    for name, res in ls.bones.items():
        assert res.side == "r", name
        assert "side_mismatch" not in res.flags and "name_mismatch" not in res.flags, (name, res.flags)


def test_uncertainties_are_reported(iso_cases):
    J = iso_cases[0]["joints"]
    for name in ("knee_r", "ankle_r"):
        assert np.all(np.linalg.eigvalsh(J[name].origin_cov) > 0)
        assert 0 < J[name].axis_sd_deg < 5


# --------------------------------------------------------------------------- equivariance
@pytest.fixture(scope="module")
def seed0_meshes(iso_cases):
    return iso_cases[0]["meshes"]


@pytest.fixture(scope="module")
def seed0_result(seed0_meshes):
    ls = detect_landmarks(seed0_meshes)
    return ls, joints_from_landmarks(ls)[0]


def _ang(a, b):
    return np.degrees(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0)))


def test_rigid_motion_moves_every_output(seed0_meshes, seed0_result):
    ls0, J0 = seed0_result
    R = Rotation.from_rotvec([0.9, -1.7, 0.4]).as_matrix()
    t = np.array([0.31, -0.12, 0.57])
    moved = {}
    for k, m in seed0_meshes.items():
        moved[k] = trimesh.Trimesh(np.asarray(m.vertices) @ R.T + t, np.asarray(m.faces), process=False)
    ls1 = detect_landmarks(moved)
    J1, _ = joints_from_landmarks(ls1)
    assert set(ls1.bones) == set(ls0.bones)
    n = 0
    for b, r0 in ls0.bones.items():
        r1 = ls1.bones[b]
        assert set(r1.landmarks) == set(r0.landmarks), b
        for k, l0 in r0.landmarks.items():
            err = np.linalg.norm(r1.landmarks[k].position - (R @ l0.position + t))
            assert err < 1e-5, f"{b}.{k}: {err * 1e3:.4f} mm"
            n += 1
        for k, a0 in r0.axes.items():
            assert _ang(r1.axes[k].direction, R @ a0.direction) < 0.01, f"{b}.{k}"
    for k, j0 in J0.items():
        assert np.linalg.norm(J1[k].origin - (R @ j0.origin + t)) < 1e-5, k
        for c in range(3):
            assert _ang(J1[k].rotation[:, c], R @ j0.rotation[:, c]) < 0.01, k
    assert n > 20


def test_mirrored_left_gives_mirrored_result(seed0_meshes, seed0_result):
    ls0, J0 = seed0_result
    M = np.diag([-1.0, 1.0, 1.0])                     # reflection through the scanner's y-z plane
    mirrored = {}
    for k, m in seed0_meshes.items():
        mirrored[k[:-2] + "_l"] = trimesh.Trimesh(np.asarray(m.vertices) @ M, np.asarray(m.faces)[:, ::-1],
                                                  process=False)
    ls1 = detect_landmarks(mirrored)
    J1, _ = joints_from_landmarks(ls1)
    for b, r0 in ls0.bones.items():
        r1 = ls1.bones[b[:-2] + "_l"]
        assert r1.side == "l"
        for k, l0 in r0.landmarks.items():
            k1 = "L" + k[1:] if k[0] == "R" and k[1:2].isupper() else k
            assert np.linalg.norm(r1.landmarks[k1].position - M @ l0.position) < 1e-5, f"{b}.{k}"
    rightward = ("hip", "knee", "ankle", "mtp")
    for k, j0 in J0.items():
        j1 = J1[k[:-2] + "_l"]
        assert np.linalg.norm(j1.origin - M @ j0.origin) < 1e-5, k
        z = M @ j0.rotation[:, 2]
        z = -z if k.startswith(rightward) else z       # "to the subject's right" flips with the side
        assert _ang(j1.rotation[:, 2], z) < 0.01, k


def test_missing_bone_drops_only_its_joints(seed0_meshes):
    partial = {k: v for k, v in seed0_meshes.items() if k != "talus_r"}
    ls = detect_landmarks(partial)
    J, dropped = joints_from_landmarks(ls)
    assert "knee_r" in J and "mtp_r" in J
    assert "ankle_r" not in J and "subtalar_r" not in J
    assert "talus_r" in dropped["ankle_r"] and "talus_r" in ls.missing


# --------------------------------------------------------------------------- truncation
@pytest.mark.parametrize("part", ["proximal", "distal"])
def test_truncated_femur_is_flagged_and_still_detected(part):
    from phantoms.anatomy import make_phantom
    from phantoms.imaging import label_volume
    from personalize.io import LabelVolume
    from personalize.surfaces import surfaces_from_labels

    ph = make_phantom(seed=4)
    truth = ph.truth()["landmarks"]["bones"]["femur_r"]["landmarks"]
    labels, aff, lmap = label_volume(ph, voxel=(1e-3,) * 3, bones=["femur_r"], fov=("femur_r", 0.0, 0.55))
    vol = LabelVolume(labels=labels, affine_m=np.diag([1e-3, 1e-3, 1e-3, 1.0]) @ aff, label_map=lmap, source="fov")
    mesh = surfaces_from_labels(vol, workers=1)["femur_r"].mesh
    # keep the requested half: the FOV fraction runs along an image axis whose sign we do not assume
    head = np.asarray(truth["femoral_head_centre"]["position"])
    has_head = np.min(np.linalg.norm(np.asarray(mesh.vertices) - head, axis=1)) < 0.03
    if (part == "proximal") != has_head:
        labels, aff, lmap = label_volume(ph, voxel=(1e-3,) * 3, bones=["femur_r"], fov=("femur_r", 0.45, 1.0))
        vol = LabelVolume(labels=labels, affine_m=np.diag([1e-3, 1e-3, 1e-3, 1.0]) @ aff, label_map=lmap,
                          source="fov")
        mesh = surfaces_from_labels(vol, workers=1)["femur_r"].mesh
    res = detect_landmarks({"femur_r": mesh}).bones["femur_r"]
    assert "truncated" in res.flags
    assert res.side == "r"
    if part == "proximal":
        err = np.linalg.norm(res.landmarks["femoral_head_centre"].position
                             - np.asarray(truth["femoral_head_centre"]["position"]))
        assert err < 5e-4
        assert "intercondylar_midpoint" not in res.landmarks
    else:
        err = np.linalg.norm(res.landmarks["intercondylar_midpoint"].position
                             - np.asarray(truth["intercondylar_midpoint"]["position"]))
        assert err < 2e-3
        assert "femoral_head_centre" not in res.landmarks


# --------------------------------------------------------------------------- neighbours
def test_flat_tibial_plateau_under_the_femur_is_not_a_cut():
    """A phantom whose flat tibial plateau passes the field-of-view-cut test (validation subject 12 of seed 2026).

    From the tibia's shape alone the plateau looks like a planar cut, the
    proximal end flips and the talar dome is lost (ankle axis 85 deg off
    before the fix).  With the femur and the talus of the same scan the end
    under the femur is proximal and is not a cut.
    """
    from personalize.landmarks.surface import as_surface
    from personalize.landmarks.tibia import detect_tibia
    from personalize.evaluation.phantom_set import draw_subjects

    spec = draw_subjects(20, 2026)[11]
    case = phantom_case(spec.seed, voxel=tuple(v * 1e-3 for v in spec.voxel_mm), noise=spec.segmentation_noise,
                        params=spec.params, bones=("femur", "tibia", "fibula", "talus", "calcn"))
    alone, _ = detect_tibia(as_surface(case["meshes"]["tibia_r"], "tibia_r"), "tibia_r")
    assert "truncated" in alone.flags            # the ambiguity this test is about
    tib = case["landmarks"].bones["tibia_r"]
    assert "truncated" not in tib.flags
    from phantoms.anatomy import make_phantom
    truth = make_phantom(seed=spec.seed, **spec.params).truth()["joints"]["joints"]
    y_true = np.asarray(truth["knee_r"]["rotation"])[:, 1]
    assert tib.frames["anatomical"]["rotation"][:, 1] @ y_true > 0.99
    # the coarse-imaging limits of the issue (twice the 1 mm ones)
    assert case["errors"]["ankle_centre"] < 2 * TOLERANCES["ankle_centre"]
    assert case["errors"]["ankle_axis"] < 2 * TOLERANCES["ankle_axis"]


def test_truncated_tibia_under_the_femur_keeps_its_cut():
    """A field of view that cuts the tibia: the end under the femur is proximal and is not a cut, the other end
    stays a cut (flagged "truncated"), and the plateau is found at the right end."""
    from phantoms.anatomy import make_phantom
    from phantoms.imaging import label_volume
    from personalize.io import LabelVolume
    from personalize.surfaces import surfaces_from_labels

    ph = make_phantom(seed=4)
    truth = ph.truth()
    plateau = np.asarray(truth["landmarks"]["bones"]["tibia_r"]["landmarks"]["plateau_centre"]["position"])
    knee = np.asarray(truth["joints"]["joints"]["knee_r"]["origin"])
    for f0, f1 in ((0.0, 0.55), (0.45, 1.0)):
        labels, aff, lmap = label_volume(ph, voxel=(1e-3,) * 3, bones=["femur_r", "tibia_r"], fov=("tibia_r", f0, f1))
        vol = LabelVolume(labels=labels, affine_m=np.diag([1e-3, 1e-3, 1e-3, 1.0]) @ aff, label_map=lmap, source="fov")
        surf = surfaces_from_labels(vol, workers=1)
        tib_mesh = surf["tibia_r"].mesh
        if np.min(np.linalg.norm(np.asarray(tib_mesh.vertices) - plateau, axis=1)) < 0.01:
            break                                  # this half holds the plateau (image axis sign not assumed)
    assert "femur_r" in surf
    # the phantom's flat plateau also looks like a cut: alone, both ends are "cuts" and no plateau is found
    from personalize.landmarks.surface import as_surface
    from personalize.landmarks.tibia import detect_tibia
    alone, _ = detect_tibia(as_surface(surf["tibia_r"].mesh, "tibia_r"), "tibia_r")
    assert "plateau_centre" not in alone.landmarks
    res = detect_landmarks(surf).bones["tibia_r"]
    assert "truncated" in res.flags
    assert np.linalg.norm(res.landmarks["plateau_centre"].position - plateau) < 3e-3
    # proximal axis points from the cut towards the knee
    y = res.frames["anatomical"]["rotation"][:, 1]
    assert (knee - res.axes["shaft_axis"].point) @ y > 0


def test_juvenile_bones_meet_the_adult_limits():
    # a 1.2 m child: small bones, the femoral anteversion and neck-shaft angle of
    # a young child, little tibial torsion; detectors have no adult-size assumption
    # beyond their radius ranges (checked here at their small end)
    params = dict(stature=1.2, femoral_anteversion_deg=35.0, neck_shaft_deg=145.0, tibial_torsion_deg=12.0)
    case = phantom_case(0, voxel=(1e-3, 1e-3, 1e-3), noise=0.0, params=params)
    for metric in ("hip_centre", "knee_centre", "knee_axis", "ankle_centre", "ankle_axis", "subtalar_axis",
                   "ground_contacts"):
        err = case["errors"][metric]
        assert err <= TOLERANCES[metric], f"{metric} error {err:.3f} > {TOLERANCES[metric]}"
    assert not any(case["flags"].values()), case["flags"]


def test_juvenile_bones_with_open_growth_plates():
    # a child's MRI bone labels stop at the growth plates: the femoral head, the distal
    # femur and both tibial ends are separate pieces 1.5 mm from their shafts.  They are
    # joined back (the capital epiphysis, ~7 % of this femur, used to be dropped as an
    # island, and the hip centre then came from the neck, 39 mm off)
    params = dict(stature=1.2, femoral_anteversion_deg=35.0, neck_shaft_deg=145.0, tibial_torsion_deg=12.0)
    case = phantom_case(1, voxel=(1e-3, 1e-3, 1e-3), noise=0.0, params=params, physes=1.5e-3)
    for bone in ("femur_r", "tibia_r"):
        rep = case["surfaces"][bone].report
        assert len(rep["epiphyses_joined"]) == 2 and rep["islands_removed"] == [], (bone, rep)
        assert len(case["meshes"][bone].split(only_watertight=False)) == 1
    for metric in ("hip_centre", "knee_centre", "knee_axis", "ankle_centre", "ankle_axis", "subtalar_axis",
                   "ground_contacts"):
        err = case["errors"][metric]
        assert err <= TOLERANCES[metric], f"{metric} error {err:.3f} > {TOLERANCES[metric]}"
    assert not any(case["flags"].values()), case["flags"]
