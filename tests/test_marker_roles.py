"""A Plug-in-Gait set under a lab's own labels takes Plug-in-Gait's THI / TIB / TOE roles (`canonical_names`)."""
from kinematics.io.marker_sets import MarkerDef, MarkerSet, canonical_names, preset


def _renamed_pig(extra_thigh: bool = False) -> MarkerSet:
    m = {}
    for S, s in (("R", "r"), ("L", "l")):
        m.update({f"{S}_ASIS": MarkerDef("pelvis", f"{S}ASI"), f"{S}_PSIS": MarkerDef("pelvis", f"{S}PSI"),
                  f"{S}_THIGH": MarkerDef(f"femur_{s}"), f"{S}_KNEE": MarkerDef(f"femur_{s}", f"{S}KNE"),
                  f"{S}_SHANK": MarkerDef(f"tibia_{s}"), f"{S}_ANKLE": MarkerDef(f"tibia_{s}", f"{S}ANK"),
                  f"{S}_HEEL": MarkerDef(f"calcn_{s}", f"{S}HEE"), f"{S}_TOE2": MarkerDef(f"calcn_{s}"),
                  f"{S}_MT1": MarkerDef(f"calcn_{s}", f"{S}D1M")})
    if extra_thigh:
        m["R_THIGH2"] = MarkerDef("femur_r")
    return MarkerSet("lab_own", m)


def test_renamed_plug_in_gait_set_takes_the_wand_and_toe_roles():
    ms = _renamed_pig()
    names = canonical_names(ms, list(ms.markers) + ["R_MT5"])
    assert {k: names[k] for k in ("R_THIGH", "R_SHANK", "R_TOE2", "L_THIGH", "L_SHANK", "L_TOE2")} == {
        "R_THIGH": "RTHI", "R_SHANK": "RTIB", "R_TOE2": "RTOE", "L_THIGH": "LTHI", "L_SHANK": "LTIB", "L_TOE2": "LTOE"}
    assert names["R_KNEE"] == "RKNE" and names["R_MT1"] == "RD1M" and names["R_MT5"] == "R_MT5"


def test_two_skin_markers_on_a_thigh_leave_that_side_without_roles():
    names = canonical_names(_renamed_pig(extra_thigh=True), list(_renamed_pig(True).markers))
    assert names["R_THIGH"] == "R_THIGH" and names["R_SHANK"] == "R_SHANK" and names["R_TOE2"] == "R_TOE2"
    assert names["L_THIGH"] == "LTHI"                  # the other side is still unambiguous


def test_presets_with_clusters_or_landmark_sets_get_no_roles():
    for p in ("ior", "cast", "opensim"):
        names = canonical_names(preset(p), list(preset(p).markers))
        assert not any(v[1:] in ("THI", "TIB", "TOE") for v in names.values()), p
