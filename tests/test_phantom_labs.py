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
