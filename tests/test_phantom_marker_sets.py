"""Marker sets as data (kinematics.io.marker_sets): presets, markers.json round trip, bad files."""
from __future__ import annotations

import json

import pytest

from lowerlimb.errors import InputError
from kinematics.io.marker_sets import PRESETS, preset, read_marker_set, resolve_marker_set, write_marker_set


def test_presets_have_both_sides_and_landmark_names():
    ior = preset("ior")
    for S, s in (("R", "r"), ("L", "l")):
        for m in ("TRO", "MFC", "TUB", "HFB", "SHN", "MMA", "P1M", "P5M", "D1M", "D5M", "HEE", "LCA"):
            assert f"{S}{m}" in ior.markers
        assert ior.markers[f"{S}TUB"].segment == f"tibia_{s}" and ior.markers[f"{S}TUB"].landmark == f"{S}TTB"
        assert ior.markers[f"{S}HFB"].segment == f"tibia_{s}"          # a fibula landmark rides on the shank
        assert ior.markers[f"{S}SHN"].landmark is None
    assert not any(k.endswith(("TIB", "THI")) for k in ior.labels)      # no wands
    cast = preset("cast")
    assert {k for k, v in cast.markers.items() if v.static_only} == {f"{S}{m}" for S in "RL" for m in
                                                                   ("TRO", "KNE", "MFC", "TUB", "HFB", "ANK", "MMA")}
    assert len(cast.on_segment("femur_r")) == 4 + 3 and len(cast.on_segment("tibia_l")) == 4 + 4
    osm = preset("opensim")
    assert osm.markers["R.Knee.Lat"].landmark == "RKNE" and osm.markers["C7" if "C7" in osm.markers else "Sternum"].segment == "torso"
    assert set(preset("pig").labels) == {f"{S}{m}" for S in "RL" for m in ("ASI", "PSI", "THI", "KNE", "TIB", "ANK", "HEE", "TOE")}


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_markers_json_round_trip(tmp_path, name):
    ms = preset(name)
    p = write_marker_set(tmp_path / "markers.json", ms)
    back = read_marker_set(p)
    assert back == ms
    assert resolve_marker_set(str(p)) == ms and resolve_marker_set(name) == ms


def test_issue_example_reads(tmp_path):
    p = tmp_path / "markers.json"
    p.write_text(json.dumps({"name": "lab", "markers": {"RTUB": {"segment": "tibia_r", "landmark": "RTTB"},
                                                        "RSHN": {"segment": "tibia_r"}, "C7": {"segment": "torso"}}}))
    ms = read_marker_set(p)
    assert ms.name == "lab" and ms.landmark("RTUB") == "RTTB" and ms.landmark("RSHN") is None
    assert ms.segment("C7") == "torso" and ms.dynamic_labels() == ("RTUB", "RSHN", "C7")


@pytest.mark.parametrize("content,msg", [
    ("{not json", "not valid JSON"),
    (json.dumps({"name": "x"}), "expected"),
    (json.dumps({"markers": {"A": {"landmark": "RASI"}}}), "needs a \"segment\""),
    (json.dumps({"markers": {"A": {"segment": "pelvis", "colour": 1}}}), "unknown key"),
])
def test_bad_markers_json(tmp_path, content, msg):
    p = tmp_path / "markers.json"
    p.write_text(content)
    with pytest.raises(InputError, match=msg) as e:
        read_marker_set(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


def test_unknown_preset():
    with pytest.raises(InputError, match="not a preset"):
        resolve_marker_set("vicon-fancy")
