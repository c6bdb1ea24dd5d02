"""Malleolar marker sites (RANK, RMMA) along the talocrural axis, where Plug-in-Gait and IOR palpate them."""
import numpy as np
import pytest

from personalize.bone_set import read_bone_set


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ICL_MRI", "LHDL_CT"])
def test_malleolar_sites_match_palpation_along_the_ankle_axis(shared_data, name):
    """The real-anatomy phantom palpates the malleoli as the extreme points along the expert's ankle axis
    (`phantoms.marker_placement.find_landmarks`).  Found along the talar dome's axis, the detected sites lie
    within 3 mm of them (ICL-MRI 2.2 / 1.8 mm, LHDL-CT 2.9 / 2.1 mm); along the knee's medial-lateral direction
    (RMMA) and the line through the malleolar tips (RANK), 17-24 deg from it, they were 6.3 / 9.2 and 2.6 /
    7.3 mm off, and the MRI ankle centre registered on them moved with their mean."""
    from phantoms.marker_placement import find_landmarks
    from phantoms.real_anatomy import load_real_anatomy
    from phantoms.real_subject import standing_coordinates

    anat = load_real_anatomy(shared_data / "bones" / name, shared_data / "reference_models" / f"manual_{name}.osim")
    palpated = find_landmarks(anat, standing_coordinates(anat))
    ls = read_bone_set(shared_data / "bones" / name).landmarks
    for bone, marker in (("fibula_r", "RANK"), ("tibia_r", "RMMA")):
        # right bodies' local frames are the scanner frame
        d = np.linalg.norm(ls.bones[bone].landmarks[marker].position - palpated[marker][1])
        assert d < 0.003, (marker, d)
