"""The analytic phantom's trials in any lab: Y-up or Z-up, any walking direction, Static.c3d, TRC, no functional trial."""
from __future__ import annotations

import json

import numpy as np
import pytest

SHORT = dict(gait_trials=1, gait_cycles=1.0, crouch_angles=(), functional_ranges=(), static_duration=0.07,
             sta=False, noise_sd=0.0)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The phantom and its trials in the default lab (X forward, Y left, Z up)."""
    from phantoms import make_phantom
    from phantoms.motion import write_trials

    ph = make_phantom(seed=5)
    ref = tmp_path_factory.mktemp("ref")
    (ref / "truth").mkdir()
    write_trials(ref, ph, 5, **SHORT)
    return ph, ref


@pytest.mark.parametrize("up,walk", [("y-up", "-z"), ("z-up", "-y")])
def test_trials_written_in_the_lab_axes(reference, tmp_path, up, walk):
    from kinematics.io.c3d import read_c3d
    from kinematics.io.storage import read_trc
    from phantoms.lab import make_lab
    from phantoms.motion import write_trials

    phantom, ref = reference
    other = tmp_path / "lab"
    other.mkdir()
    (other / "truth").mkdir()
    lab = make_lab(up, walk)
    entries = write_trials(other, phantom, 5, lab=lab, static_name="Static", trial_format="both", **SHORT)
    assert {p.name for p in other.iterdir() if p.suffix in (".c3d", ".trc")} == \
        {"Static.c3d", "Static.trc", "gait_01.c3d", "gait_01.trc"}
    a, b = read_c3d(ref / "static.c3d"), read_c3d(other / "Static.c3d")
    assert b.n_frames == 7 and a.names == b.names
    # phantom lab (X forward, Y left, Z up) -> this lab: forward -> walk, up -> up, left -> -right
    R = np.column_stack([lab.forward, -np.cross(lab.forward, lab.up), lab.up])
    np.testing.assert_allclose(b.positions, a.positions @ R.T, atol=2e-6)
    np.testing.assert_allclose(read_trc(other / "Static.trc").positions, b.positions, atol=2e-6)
    ca, cb = read_trc(ref / "truth" / "static_centres.trc"), read_trc(other / "truth" / "static_centres.trc")
    np.testing.assert_allclose(cb.positions, ca.positions @ R.T, atol=2e-6)
    # the pelvis stands about a metre up the lab's vertical; the walk goes along `walk`
    assert 0.8 < np.mean(b.marker("RASI")[0] @ lab.up) < 1.2
    g = read_c3d(other / "gait_01.c3d")
    d = np.nanmean(g.positions[-1], axis=0) - np.nanmean(g.positions[0], axis=0)
    assert d @ lab.forward > 1.0
    assert entries["motion"]["lab"]["up"] == lab.up.tolist()
    assert not any(t["kind"] == "functional" for t in entries["motion"]["trials"])
    json.dumps(entries)


def test_phantom_from_options(tmp_path):
    """The library form of ``personalize phantom``: options -> build_phantom -> write_phantom, progress step by step."""
    from lowerlimb.errors import InputError
    from personalize.evaluation.phantom_builder import PhantomOptions, build_phantom, noise_level, write_phantom

    subject = build_phantom(PhantomOptions(seed=3, side="r", bones=("patella_r",), motion=False, voxel_mm=(2, 2, 2),
                                           noise="low"))
    assert subject.steps == 3 and subject.bones == ("patella_r",) and subject.noise == noise_level("low") == 0.25
    said: list[str] = []
    out = write_phantom(subject, tmp_path / "ph", progress=said.append)
    assert said == ["rasterising patella_r", "meshing patella_r"] and len(said) <= subject.steps
    assert {p.name for p in out.iterdir()} == {"labels.nii.gz", "label_map.json", "meshes", "truth.json"}
    truth = json.loads((out / "truth.json").read_text())
    assert truth["params"]["seed"] == 3 and "femur_l" not in truth["landmarks"]["bones"]
    assert [p.name for p in (out / "meshes").iterdir()] == ["patella_r.ply"]
    for bad, message in ((PhantomOptions(side="r"), "motion trials need both legs"),
                         (PhantomOptions(noise="loud"), "not a number in 0..1"),
                         (PhantomOptions(marker_set="ior"), "Plug-in-Gait set")):
        with pytest.raises(InputError, match=message):
            build_phantom(bad)
