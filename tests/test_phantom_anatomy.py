"""Phantom anatomy: exact landmarks, congruent joints, placement, mirror symmetry, parameters."""
from __future__ import annotations

import numpy as np
import pytest

from lowerlimb.errors import InputError
from lowerlimb.bones import BONE_NAMES, SIDES, mirror_name
from lowerlimb.topology import JOINTS, sided
from phantoms import PhantomParams, make_phantom

SURFACE_LANDMARKS = {
    "pelvis": ["RASI", "LASI", "RPSI", "LPSI", "SYMP"],
    "femur_r": ["RTRO", "RKNE", "RMFC"],
    "tibia_r": ["plateau_centre", "RTTB", "RMMA", "plafond_centre"],
    "fibula_r": ["RHFB", "RANK"],
    "calcn_r": ["RHEE", "RD1M", "RD5M", "heel_contact", "met1_contact", "met5_contact"],
}
M3 = np.diag([1.0, 1.0, -1.0])


@pytest.fixture(scope="module")
def ph():
    return make_phantom(seed=3)


@pytest.fixture(scope="module")
def truth(ph):
    return ph.truth()


def _lm(truth, bone, name):
    return np.array(truth["landmarks"]["bones"][bone]["landmarks"][name]["position"])


def _axis(truth, bone, name):
    a = truth["landmarks"]["bones"][bone]["axes"][name]
    return np.array(a["point"]), np.array(a["direction"])


def test_bone_names_and_schema(ph, truth):
    assert ph.bone_names == BONE_NAMES
    assert truth["units"] == "m" and truth["frame"] == "scanner"
    bones = truth["landmarks"]["bones"]
    assert set(bones) == set(BONE_NAMES)
    assert set(truth["joints"]["joints"]) == {sided(j, s) for j in JOINTS for s in SIDES}
    for name in ("femoral_head_centre", "LTRO", "LKNE", "LMFC", "intercondylar_midpoint"):
        assert name in bones["femur_l"]["landmarks"]
    for name in ("femoral_head_radius", "neck_diameter_min", "medial_condyle_a", "lateral_condyle_b"):
        assert bones["femur_l"]["scalars"][name]["value"] > 0
    assert set(bones["talus_r"]["axes"]) == {"ankle_axis", "subtalar_axis"}
    assert set(bones["calcn_l"]["frames"]) == {"foot"}


@pytest.mark.parametrize("side", ["r", "l"])
def test_surface_landmarks_lie_on_the_surface(ph, truth, side):
    for bone, names in SURFACE_LANDMARKS.items():
        b = bone if bone == "pelvis" else bone[:-1] + side
        for n in names:
            n2 = n if side == "r" or bone == "pelvis" else mirror_name(n)
            d = ph.sdf(b, _lm(truth, b, n2)[None])[0]
            assert abs(d) < 1e-7, (b, n2, d)


def test_exact_analytic_surfaces(ph, truth):
    # every check set (acetabular cup, neck waist ring, plafond and dome arcs) is on the surface
    for key, pts in ph.surface_checks().items():
        bone = key.split(".")[0]
        assert np.abs(ph.sdf(bone, pts)).max() < 1e-7, key
    # femoral head: a sphere of the stated radius around the stated centre, away from the neck
    for side in "rl":
        c = _lm(truth, f"femur_{side}", "femoral_head_centre")
        r = truth["landmarks"]["bones"][f"femur_{side}"]["scalars"]["femoral_head_radius"]["value"]
        _, neck = _axis(truth, f"femur_{side}", "neck_axis")
        u = np.random.default_rng(0).normal(size=(400, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        u = u[u @ neck > 0.1]
        assert np.abs(ph.sdf(f"femur_{side}", c + r * u)).max() < 1e-9
        # the acetabulum is concentric with the femoral head (congruent hip)
        np.testing.assert_allclose(_lm(truth, "pelvis", f"acetabulum_centre_{side}"), c, atol=1e-12)
        ra = truth["landmarks"]["bones"]["pelvis"]["scalars"][f"acetabulum_radius_{side}"]["value"]
        assert 0.001 < ra - r < 0.004
    # neck waist: the narrowest diameter is the stated one
    ring = ph.surface_checks()["femur_r.neck_waist_ring"]
    p, dvec = _axis(truth, "femur_r", "neck_axis")
    rho = np.linalg.norm(np.cross(ring - p, dvec), axis=1)
    dmin = truth["landmarks"]["bones"]["femur_r"]["scalars"]["neck_diameter_min"]["value"]
    np.testing.assert_allclose(2 * rho, dmin, atol=1e-9)


def test_joints_are_congruent_and_defined(truth):
    J = truth["joints"]["joints"]
    for s in "rl":
        kp_f, kd_f = _axis(truth, f"femur_{s}", "knee_axis")
        kp_t, kd_t = _axis(truth, f"tibia_{s}", "knee_axis")
        np.testing.assert_allclose(kd_f, kd_t, atol=1e-12)
        assert np.linalg.norm(np.cross(kp_t - kp_f, kd_f)) < 1e-12
        ap_t, ad_t = _axis(truth, f"tibia_{s}", "ankle_axis")
        ap_a, ad_a = _axis(truth, f"talus_{s}", "ankle_axis")
        np.testing.assert_allclose(ad_t, ad_a, atol=1e-12)
        np.testing.assert_allclose(ap_t, ap_a, atol=1e-12)
        mid = (_lm(truth, f"femur_{s}", "medial_condyle_centre") + _lm(truth, f"femur_{s}", "lateral_condyle_centre")) / 2
        np.testing.assert_allclose(J[f"knee_{s}"]["origin"], mid, atol=1e-12)
        np.testing.assert_allclose(J[f"hip_{s}"]["origin"], _lm(truth, f"femur_{s}", "femoral_head_centre"), atol=1e-12)
        np.testing.assert_allclose(J[f"ankle_{s}"]["origin"], _lm(truth, f"talus_{s}", "talar_dome_centre"), atol=1e-12)
        # subtalar origin: the posterior talocalcaneal facet centre, on the subtalar axis
        sp, sd = _axis(truth, f"talus_{s}", "subtalar_axis")
        o = np.array(J[f"subtalar_{s}"]["origin"])
        assert np.linalg.norm(np.cross(o - sp, sd)) < 1e-12
        np.testing.assert_allclose(o, _lm(truth, f"talus_{s}", "posterior_facet_centre"), atol=1e-12)
        for j, axis in (("knee", kd_f), ("ankle", ad_t), ("subtalar", sd), ("mtp", _axis(truth, f"toes_{s}", "mtp_axis")[1])):
            R = np.array(J[f"{j}_{s}"]["rotation"])
            np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
            assert np.linalg.det(R) == pytest.approx(1.0)
            np.testing.assert_allclose(R[:, 2], axis, atol=1e-12)


def test_posterior_condyles_are_one_cylinder_about_the_knee_axis(ph, truth):
    # the two knee-axis conventions of issue F3 coincide on the phantom: the
    # posterior-distal arcs of both condyles (exact surface points, checked in
    # test_exact_analytic_surfaces) lie on one cylinder about the truth knee axis,
    # whose centre between the condyles is the knee joint origin
    J = truth["joints"]["joints"]
    checks = ph.surface_checks()
    for s in "rl":
        kp, kd = _axis(truth, f"femur_{s}", "knee_axis")
        arcs = checks[f"femur_{s}.posterior_condyle_arcs"]
        rho = np.linalg.norm(np.cross(arcs - kp, kd), axis=1)
        r = truth["landmarks"]["bones"][f"femur_{s}"]["scalars"]
        np.testing.assert_allclose(rho, r["medial_condyle_a"]["value"], atol=1e-12)
        assert r["lateral_condyle_a"]["value"] == r["medial_condyle_a"]["value"] == r["medial_condyle_b"]["value"]
        t = (arcs - np.array(J[f"knee_{s}"]["origin"])) @ kd
        assert abs(t.min() + t.max()) < 1e-12 and t.max() > 0.015      # origin midway between the condyles


def test_conventions_in_body_frame():
    ph = make_phantom(seed=1, placement="identity")
    t = ph.truth()
    J = t["joints"]["joints"]
    for s in "rl":
        for j in ("hip", "knee", "ankle", "mtp"):
            R = np.array(J[f"{j}_{s}"]["rotation"])
            assert R[2, 2] > 0.8, (j, s)          # Z to the subject's right
            assert R[1, 1] > 0.7, (j, s)          # Y superior
            assert R[0, 0] > 0.7, (j, s)          # X anterior
        assert np.array(J[f"subtalar_{s}"]["rotation"])[0, 2] > 0.5   # subtalar Z anterior
        _, sh = _axis(t, f"femur_{s}", "shaft_axis")
        assert sh[1] > 0.95                         # shaft axes point proximally
        for b, n in (("femur", "RKNE"), ("fibula", "RANK")):
            name = n if s == "r" else mirror_name(n)
            z = _lm(t, f"{b}_{s}", name)[2]
            assert (z > 0) == (s == "r")            # right landmarks on the right
        # the plantar support plane touches the three contact points from below
        c = t["landmarks"]["bones"][f"calcn_{s}"]["landmarks"]
        foot = t["landmarks"]["bones"][f"calcn_{s}"]["frames"]["foot"]
        n = np.array(foot["rotation"])[:, 1]
        for k in ("met1_contact", "met5_contact"):
            assert abs((np.array(c[k]["position"]) - np.array(c["heel_contact"]["position"])) @ n) < 1e-12
        assert n[1] > 0.999


def test_support_plane_is_tangent_from_below():
    ph = make_phantom(seed=2, side="r")
    t = ph.truth()
    foot = t["landmarks"]["bones"]["calcn_r"]["frames"]["foot"]
    o, n = np.array(foot["origin"]), np.array(foot["rotation"])[:, 1]
    # sample the bone's interior: no point below the plane
    lo, hi = ph.bounds("calcn_r")
    p = lo + np.random.default_rng(0).random((200_000, 3)) * (hi - lo)
    inside = p[ph.sdf("calcn_r", p) < 0]
    assert len(inside) > 1000
    assert ((inside - o) @ n).min() > -1e-6


def test_placement_moves_truth_rigidly():
    a = make_phantom(seed=5, placement="identity")
    b = make_phantom(seed=5)                               # random placement from the seed
    A = b.placement
    R, tr = A[:3, :3], A[:3, 3]
    # bones are not aligned with the image axes
    assert np.abs(R).max(axis=0).max() < np.cos(np.deg2rad(5))
    ta, tb = a.truth(), b.truth()
    for bone in BONE_NAMES:
        ba, bb = ta["landmarks"]["bones"][bone], tb["landmarks"]["bones"][bone]
        for k, v in ba["landmarks"].items():
            np.testing.assert_allclose(bb["landmarks"][k]["position"], R @ v["position"] + tr, atol=1e-12)
        for k, v in ba["axes"].items():
            np.testing.assert_allclose(bb["axes"][k]["direction"], R @ v["direction"], atol=1e-12)
        for k, v in ba["frames"].items():
            np.testing.assert_allclose(bb["frames"][k]["rotation"], R @ np.array(v["rotation"]), atol=1e-12)
    for k, v in ta["joints"]["joints"].items():
        np.testing.assert_allclose(tb["joints"]["joints"][k]["origin"], R @ v["origin"] + tr, atol=1e-12)
    p = np.random.default_rng(1).normal(scale=0.05, size=(50, 3)) + ta["landmarks"]["bones"]["femur_r"]["landmarks"]["RTRO"]["position"]
    np.testing.assert_allclose(b.sdf("femur_r", p @ R.T + tr), a.sdf("femur_r", p), atol=1e-12)


def test_mirror_symmetry_without_asymmetry():
    ph = make_phantom(seed=4, asymmetry=0.0, variation=0.0, placement="identity")
    t = ph.body_truth()["bones"]
    for bone in BONE_NAMES:
        if not bone.endswith("_r"):
            continue
        left = mirror_name(bone)
        for k, v in t[bone]["landmarks"].items():
            np.testing.assert_allclose(t[left]["landmarks"][mirror_name(k)], M3 @ v, atol=1e-12)
        for k, s in t[bone]["scalars"].items():
            assert t[left]["scalars"][mirror_name(k)] == pytest.approx(s)
        p = t[bone]["landmarks"].get("RTRO", None)
    p = np.random.default_rng(0).normal(scale=0.06, size=(300, 3)) + [0, 0.5, 0.08]
    for b in ("femur_r", "tibia_r", "talus_r", "calcn_r"):
        np.testing.assert_allclose(ph.sdf(mirror_name(b), p @ M3), ph.sdf(b, p), atol=1e-12)
    q = np.random.default_rng(1).normal(scale=0.08, size=(300, 3)) + [-0.05, 0.95, 0.0]
    np.testing.assert_allclose(ph.sdf("pelvis", q @ M3), ph.sdf("pelvis", q), atol=1e-12)


@pytest.mark.parametrize("anteversion,neck_shaft,torsion", [(13.0, 128.0, 25.0), (30.0, 140.0, 5.0)])
def test_angle_parameters_are_realised(anteversion, neck_shaft, torsion):
    ph = make_phantom(seed=0, placement="identity", femoral_anteversion_deg=anteversion,
                      neck_shaft_deg=neck_shaft, tibial_torsion_deg=torsion, asymmetry=0.04)
    t = ph.truth()
    for s in "rl":
        _, n = _axis(t, f"femur_{s}", "neck_axis")
        _, sh = _axis(t, f"femur_{s}", "shaft_axis")
        _, k = _axis(t, f"femur_{s}", "knee_axis")
        assert np.degrees(np.arccos(n @ sh)) == pytest.approx(180 - neck_shaft, abs=1e-9)
        # anteversion: neck vs condylar axis, both projected on the plane normal to the shaft
        P = np.eye(3) - np.outer(sh, sh)
        med = -k if s == "r" else k                         # medial direction
        nn, kk = P @ n, P @ med
        ang = np.degrees(np.arctan2(np.cross(kk, nn) @ sh, kk @ nn))
        assert abs(ang) == pytest.approx(anteversion, abs=1e-9)
        assert (n[0] > 0) == (anteversion > 0)              # the neck points anteriorly
        # tibial torsion: ankle vs knee axis in the transverse plane
        _, a = _axis(t, f"tibia_{s}", "ankle_axis")
        a2, k2 = a[[0, 2]], k[[0, 2]]
        tors = np.degrees(np.arccos(a2 @ k2 / np.linalg.norm(a2) / np.linalg.norm(k2)))
        assert tors == pytest.approx(torsion, abs=1e-9)
        lateral_ankle = a if s == "r" else -a
        assert lateral_ankle[0] < 0                         # external: lateral malleolus posterior


def test_sizes_scale_with_stature_and_asymmetry():
    def femur_length(ph, s):
        t = ph.body_truth()["bones"][f"femur_{s}"]["landmarks"]
        return np.linalg.norm(t["femoral_head_centre"] - t["intercondylar_midpoint"])

    a = make_phantom(seed=0, variation=0.0, asymmetry=0.0, placement="identity")
    b = make_phantom(seed=0, variation=0.0, asymmetry=0.0, stature=1.50, placement="identity")
    c = make_phantom(seed=0, variation=0.0, asymmetry=0.06, placement="identity")
    assert 0.40 < femur_length(a, "r") < 0.46
    assert femur_length(b, "r") / femur_length(a, "r") == pytest.approx(1.50 / 1.75, rel=1e-9)
    assert femur_length(c, "r") / femur_length(c, "l") == pytest.approx(1.03 / 0.97, rel=1e-9)
    r = a.truth()["landmarks"]["bones"]["femur_r"]["scalars"]["femoral_head_radius"]["value"]
    assert 0.020 < r < 0.027
    # random variation: different seeds give different subjects, same seed the same
    d1, d2, d3 = (make_phantom(seed=s, placement="identity") for s in (10, 11, 10))
    assert femur_length(d1, "r") != femur_length(d2, "r")
    assert femur_length(d1, "r") == femur_length(d3, "r")


def test_mesh_is_exact_watertight_and_outward():
    ph = make_phantom(seed=0, side="r")
    for bone in ("patella_r", "talus_r"):
        m = ph.mesh(bone)
        assert m.is_watertight and m.is_winding_consistent
        assert m.volume > 0
        assert np.abs(ph.sdf(bone, m.vertices)).max() < 1e-6
        err = np.abs(ph.sdf(bone, m.triangles_center))
        assert np.median(err) < 5e-6 and np.percentile(err, 99) < 5e-5
        # outward normals: stepping along the normal leaves the bone
        fc, fn = m.triangles_center[::50], m.face_normals[::50]
        assert np.mean(ph.sdf(bone, fc + 2e-4 * fn) > 0) > 0.99
    assert ph.mesh("patella_r") is not ph.mesh("patella_r")   # copies of a cached mesh
    # exact Euclidean distance to the reference surface along face normals
    m = ph.mesh("talus_r")
    fc, fn = m.triangles_center[::40], m.face_normals[::40]
    for off in (-1e-3, 2e-3):
        np.testing.assert_allclose(ph.surface_distance("talus_r", fc + off * fn), off, atol=2e-4)
    assert np.median(np.abs(ph.surface_distance("talus_r", fc + 1e-3 * fn) - 1e-3)) < 1e-6


def test_bad_parameters_raise_input_error():
    with pytest.raises(InputError, match="stature"):
        make_phantom(stature=175)
    with pytest.raises(InputError, match="unknown phantom parameter"):
        make_phantom(femur_len=0.4)
    with pytest.raises(InputError, match="side"):
        make_phantom(side="x")
    with pytest.raises(InputError, match="placement"):
        make_phantom(placement=np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(InputError):
        make_phantom().sdf("humerus", np.zeros((1, 3)))
    assert PhantomParams().stature == 1.75


def test_posed_bones_carry_their_truth():
    from phantoms.bone_shapes import axis_rotation

    ph = make_phantom(seed=0, side="r", placement="identity")
    t0 = ph.truth()
    # flex the knee 30 degrees about the knee axis: move tibia, fibula and everything distal
    k_pt, k_dir = _axis(t0, "femur_r", "knee_axis")
    G = np.eye(4)
    G[:3, :3] = axis_rotation(k_dir, np.deg2rad(30))
    G[:3, 3] = k_pt - G[:3, :3] @ k_pt
    distal = ("tibia_r", "fibula_r", "talus_r", "calcn_r", "toes_r")
    moved = ph.posed({b: G @ ph.body_from_local[b] for b in distal})
    t1 = moved.truth()
    rmma0, rmma1 = _lm(t0, "tibia_r", "RMMA"), _lm(t1, "tibia_r", "RMMA")
    np.testing.assert_allclose(rmma1, G[:3, :3] @ rmma0 + G[:3, 3], atol=1e-12)
    assert abs(moved.sdf("tibia_r", rmma1[None])[0]) < 1e-9
    np.testing.assert_allclose(_lm(t1, "femur_r", "RKNE"), _lm(t0, "femur_r", "RKNE"))
    # the knee joint frame stays with the femur; the ankle frame turns with the tibia
    R0 = np.array(t0["joints"]["joints"]["ankle_r"]["rotation"])
    R1 = np.array(t1["joints"]["joints"]["ankle_r"]["rotation"])
    np.testing.assert_allclose(R1, G[:3, :3] @ R0, atol=1e-12)
    np.testing.assert_allclose(t1["joints"]["joints"]["knee_r"]["rotation"], t0["joints"]["joints"]["knee_r"]["rotation"])


# --------------------------------------------------------------------------- subtalar geometry (issue F3)
@pytest.mark.parametrize("side", ["r", "l"])
def test_subtalar_axis_is_carried_by_the_talar_surfaces(ph, truth, side):
    """Parr et al. 2012: the axis joins the talar head and posterior-facet sphere centres."""
    b = f"talus_{side}"
    hc, fc = _lm(truth, b, "talar_head_centre"), _lm(truth, b, "posterior_facet_centre")
    sc = truth["landmarks"]["bones"][b]["scalars"]
    rh, rf = sc["talar_head_radius"]["value"], sc["posterior_facet_radius"]["value"]
    p, d = _axis(truth, b, "subtalar_axis")
    # both centres on the truth axis, which points from the facet to the head (anteriorly)
    for c in (hc, fc):
        assert np.linalg.norm(np.cross(c - p, d)) < 1e-12
    np.testing.assert_allclose(d, (hc - fc) / np.linalg.norm(hc - fc), atol=1e-12)
    assert 0.035 < np.linalg.norm(hc - fc) < 0.06 and 0.009 < rh < 0.015 and 0.018 < rf < 0.028
    # the head is convex (outside the sphere is outside the bone), the facet concave
    hp, fp = ph.surface_checks()[f"{b}.talar_head"], ph.surface_checks()[f"{b}.posterior_facet"]
    for pts, c, r in ((hp, hc, rh), (fp, fc, rf)):
        np.testing.assert_allclose(np.linalg.norm(pts - c, axis=1), r, atol=1e-12)
        assert np.abs(ph.sdf(b, pts)).max() < 1e-9
    out_h = hc + 1.002 * (hp - hc)
    out_f = fc + 0.998 * (fp - fc)
    assert np.all(ph.sdf(b, out_h) > 0) and np.all(ph.sdf(b, out_f) > 0)
    # the facet faces down onto the calcaneus, which carries the matching convex facet
    J = truth["joints"]["joints"]
    up = np.array(J[f"ankle_{side}"]["rotation"])[:, 1]
    assert np.all((fp - fc) @ up > 0.8 * rf)
    gap = ph.sdf(f"calcn_{side}", fp)
    assert np.all(gap > 0.0005) and np.all(gap < 0.003), gap
    # the joint origin is the posterior facet centre (on the axis)
    o = np.array(J[f"subtalar_{side}"]["origin"])
    np.testing.assert_allclose(o, _lm(truth, b, "posterior_facet_centre"), atol=1e-12)
    assert np.linalg.norm(np.cross(o - p, d)) < 1e-12


def test_talus_is_one_solid_with_cartilage_gaps(ph):
    m = ph.mesh("talus_r")
    assert m.is_watertight and m.body_count == 1
    V = np.asarray(m.vertices)
    for other in ("tibia_r", "fibula_r", "calcn_r"):
        assert ph.sdf(other, V).min() >= 0.0005, other


@pytest.mark.parametrize("voxel", [(1e-3, 1e-3, 1e-3), (0.5e-3, 0.5e-3, 2e-3)])
def test_tibia_and_talus_rasterise_as_one_piece(ph, voxel):
    from scipy import ndimage

    from phantoms.imaging import label_volume

    labels, _, lmap = label_volume(ph, voxel=voxel, bones=["tibia_r", "talus_r", "calcn_r"])
    for b in ("tibia_r", "talus_r", "calcn_r"):
        assert ndimage.label(labels == lmap[b])[1] == 1, b
