"""A subject recorded in a Y-up lab walking along -Z: model.osim in OpenSim's conventions and OpenSim's IK tool.

The phantom's trials are written in the lab's axes (`phantoms.motion.write_trials` with a `phantoms.lab.Lab`);
the pipeline reads the lab from them, builds the model in OpenSim's ground and writes every trial as TRC with an
IK setup.  Measured (seed 3, 2 mm labels): gravity (0, -9.80665, 0), standing pelvis_ty 0.95 m, standing
coordinates within 10 deg of zero (hip flexion 9.6 deg, the largest) but the ISB pelvis tilt (the phantom's
ASIS-PSIS plane, -12.0 deg), OpenSim's IK tool on the whole gait trial within 0.004 deg of personalize's on every
rotational coordinate (marker RMS 2.8552 mm both).  Slow: about 300 s on two loaded cores.
"""
from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def y_up_run(tmp_path_factory):
    from personalize.evaluation.phantom_subject import SHORT_TRIALS
    from personalize.pipeline import run_subject
    from phantoms import make_phantom
    from phantoms.lab import Lab
    from phantoms.subject import write_subject

    root = tmp_path_factory.mktemp("y_up_model")
    lab = Lab("y-up", np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, -1.0]), np.array([0.3, 0.0, 1.5]))
    subj = root / "subject"
    write_subject(subj, make_phantom(seed=3), voxel=(2e-3,) * 3, seed=3, meshes=False,
                  trials={**SHORT_TRIALS, "lab": lab})
    out = root / "out"
    return subj, out, run_subject(subj, out, report=False)


def test_y_up_lab_model_in_opensim_conventions(y_up_run, opensim, tmp_path):
    from kinematics.io.opensim_io import run_opensim_ik_tool
    from kinematics.io.storage import read_mot, read_trc

    subj, out, summary = y_up_run
    assert summary["lab"]["up"] == "+Y" and summary["lab"]["walking"] == "-Z"
    om = opensim.Model(str(out / "model.osim"))
    s = om.initSystem()
    g = om.getGravity()
    assert [g.get(i) for i in range(3)] == pytest.approx([0.0, -9.80665, 0.0])
    cs = om.getCoordinateSet()
    q = {cs.get(i).getName(): cs.get(i).getValue(s) for i in range(cs.getSize())}      # the standing pose
    assert 0.7 < q["pelvis_ty"] < 1.2
    rot = [n for n in q if cs.get(n).getMotionType() == 1]
    for n in rot:
        if n != "pelvis_tilt" and not n.startswith("mtp"):
            assert abs(np.degrees(q[n])) < 10.0, (n, np.degrees(q[n]))
    assert -20.0 < np.degrees(q["pelvis_tilt"]) < -5.0        # the ISB pelvis frame: the ASIS-PSIS plane's tilt
    # the written trial is in the model's ground: Y up, walking along +X
    trc = read_trc(out / "kinematics" / "gait_01.trc")
    sacrum = 0.5 * (trc.marker("RPSI") + trc.marker("LPSI"))
    assert np.nanmedian(sacrum[:, 1]) > 0.7 and sacrum[-1, 0] - sacrum[0, 0] > 0.5
    mine = read_mot(out / "kinematics" / "gait_01.mot")
    t0 = float(mine.time[5])
    ref = run_opensim_ik_tool(out / "kinematics" / "gait_01_ik_setup.xml", tmp_path, (t0, t0 + 0.2))
    assert len(ref["time"]) >= 15
    for c in rot:
        q_os = np.degrees(ref["q"][:, ref["coordinates"].index(c)])
        q_me = np.interp(ref["time"], mine.time, mine.values[:, mine.columns.index(c)])
        assert np.max(np.abs(q_os - q_me)) < 0.5, c
    # continuity over the whole trial: no branch jump
    assert np.max(np.abs(np.diff(mine.values[:, [mine.columns.index(c) for c in rot]], axis=0))) < 30.0
