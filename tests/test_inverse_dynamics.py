"""Trial inverse dynamics (subject01_walk1 on subject01_simbody.osim) against OpenSim's InverseDynamicsTool."""
from __future__ import annotations

import numpy as np
import pytest

from kinematics.errors import InputError

GAIT = "opensim_gait2392"
LEG_JOINTS = ("hip_flexion", "hip_adduction", "hip_rotation", "knee_angle", "ankle_angle", "subtalar_angle", "mtp_angle")


@pytest.fixture(scope="module")
def trial(shared_data):
    from kinematics.external_loads import read_external_loads
    from kinematics.inverse_dynamics import coordinate_kinds
    from kinematics.opensim_io import load_osim
    from kinematics.storage import read_mot

    d = shared_data / GAIT
    model = load_osim(d / "subject01_simbody.osim")
    kinds = coordinate_kinds(model)
    tab = read_mot(d / "subject01_walk1_ik.mot").to_radians(
        [c for c, k in zip(model.coordinate_names, kinds) if k == "rotational"])
    loads = read_external_loads(d / "subject01_walk1_grf.xml", d / "subject01_walk1_grf.mot")
    return model, tab, loads


@pytest.fixture(scope="module")
def result(trial):
    from kinematics.inverse_dynamics import trial_inverse_dynamics

    model, tab, loads = trial
    return trial_inverse_dynamics(model, tab.time, tab.select(model.coordinate_names), loads, cutoff=6.0,
                                  start=0.4, end=1.6)


def _rel_rms(res, table):
    out = {}
    for i, lab in enumerate(res.labels):
        ref = np.interp(res.time, table.time, table.column(lab))
        out[lab] = np.sqrt(np.mean((res.tau[:, i] - ref) ** 2)) / np.abs(ref).max()
    return out


def test_loads_read_and_pelvis_translations(trial):
    model, tab, loads = trial
    from kinematics.inverse_dynamics import coordinate_kinds

    assert [ld.body for ld in loads] == ["calcn_r", "calcn_l"]
    assert loads[0].force.shape == (1501, 3) and loads[0].force[:, 1].max() > 700  # N, Y up
    kinds = coordinate_kinds(model)
    assert [c for c, k in zip(model.coordinate_names, kinds) if k == "translational"] == ["pelvis_tx", "pelvis_ty", "pelvis_tz"]
    assert tab.time[0] == 0.5  # this IK result starts at 0.5 s


def test_matches_opensim_inverse_dynamics_tool(trial, result, opensim, shared_data, tmp_path):
    """OpenSim's InverseDynamicsTool on the same files in the same test: every column within 0.01 % of its peak."""
    from kinematics.storage import read_sto

    d = shared_data / GAIT
    tool = opensim.InverseDynamicsTool()
    om = opensim.Model(str(d / "subject01_simbody.osim"))  # keep a reference: the tool does not own it
    tool.setModel(om)
    tool.setCoordinatesFileName(str(d / "subject01_walk1_ik.mot"))
    tool.setExternalLoadsFileName(str(d / "subject01_walk1_grf.xml"))
    tool.setLowpassCutoffFrequency(6.0)
    tool.setStartTime(0.5)  # OpenSim would also report its padded (reflected) frames before 0.5 s
    tool.setEndTime(1.6)
    excluded = opensim.ArrayStr()
    excluded.append("muscles")
    tool.setExcludedForces(excluded)
    tool.setResultsDir(str(tmp_path))
    tool.setOutputGenForceFileName("id.sto")
    assert tool.run()
    ref = read_sto(tmp_path / "id.sto")
    assert ref.n_frames == result.time.shape[0] == 67
    rel = _rel_rms(result, ref)
    assert len(rel) == 23
    worst = max(rel, key=rel.get)
    assert rel[worst] < 1e-4, (worst, rel[worst])  # measured 9e-6


def test_matches_stored_opensim_result(result, shared_data):
    """The stored result: leg joint moments within 2 % of their peak (RMS over the common frames).

    The stored file comes from another OpenSim version: OpenSim 4's own tool run on the same files
    differs from it by the same amounts as the engine does (lumbar rotation 5.5-5.7 %, pelvis rotation
    3.3-3.4 %, pelvis tilt 1.7-2.6 %, mtp 1.3 %; knee and ankle 0.03 %), while the engine matches
    OpenSim 4's tool to 1e-5 (test above).  Its frames before 0.5 s are OpenSim's padding (the IK
    result starts at 0.5 s); the engine reports measured frames only.
    """
    from kinematics.storage import read_sto

    ref = read_sto(shared_data / GAIT / "subject01_walk1_InverseDynamics_opensim.sto")
    rel = _rel_rms(result, ref)
    for side in "rl":
        for j in LEG_JOINTS:
            assert rel[f"{j}_{side}_moment"] < 0.02, (j, side, rel[f"{j}_{side}_moment"])
    for lab in ("lumbar_extension_moment", "lumbar_bending_moment"):
        assert rel[lab] < 0.02, (lab, rel[lab])
    assert max(rel.values()) < 0.06


def test_powers_per_kg_and_sto(result, tmp_path):
    from kinematics.inverse_dynamics import write_inverse_dynamics, write_joint_powers
    from kinematics.storage import read_sto

    assert np.allclose(result.power, result.tau * result.qd)
    assert result.mass == pytest.approx(72.6, abs=0.5)
    k = result.coordinates.index("knee_angle_r")
    assert np.allclose(result.tau_per_kg[:, k] * result.mass, result.tau[:, k])
    # peak ankle plantarflexion moment of walking, ~1.5 N m/kg, and positive push-off power
    a = result.coordinates.index("ankle_angle_r")
    assert 1.0 < np.abs(result.tau_per_kg[:, a]).max() < 2.5
    path = write_inverse_dynamics(tmp_path / "id.sto", result)
    back = read_sto(path)
    assert back.columns[6] == "hip_flexion_r_moment" and back.columns[3] == "pelvis_tx_force"
    assert np.allclose(back.values, result.tau, atol=1e-6 * np.abs(result.tau).max())
    pw = read_sto(write_joint_powers(tmp_path / "p.sto", result, per_kg=True))
    assert np.allclose(pw.column("knee_angle_r_power"), result.power_per_kg[:, k], atol=1e-6)


def test_without_loads_note_and_bad_body(trial):
    from kinematics.external_loads import ExternalLoad
    from kinematics.inverse_dynamics import trial_inverse_dynamics

    model, tab, loads = trial
    q = tab.select(model.coordinate_names)
    r0 = trial_inverse_dynamics(model, tab.time, q, (), start=0.6, end=0.8)
    assert any("no external loads" in n for n in r0.notes)
    # without ground reactions the pelvis carries the body weight: residual force ~ m g
    ty = r0.coordinates.index("pelvis_ty")
    assert np.abs(r0.tau[:, ty]).mean() > 0.5 * model.total_mass * 9.81
    bad = ExternalLoad("x", "calcaneus", loads[0].time, loads[0].force, loads[0].point, loads[0].torque)
    with pytest.raises(InputError, match="calcaneus"):
        trial_inverse_dynamics(model, tab.time, q, [bad])


def test_external_loads_roundtrip_and_opensim_reads_them(trial, tmp_path, opensim):
    from kinematics.external_loads import read_external_loads, write_external_loads

    _, _, loads = trial
    mot, xml = write_external_loads(tmp_path, "grf", loads)
    back = read_external_loads(xml)
    for a, b in zip(loads, back):
        assert a.body == b.body
        for x, y in ((a.force, b.force), (a.point, b.point), (a.torque, b.torque)):
            assert np.allclose(x, y, atol=1e-6 * max(1.0, np.abs(x).max()))
    assert "N" in mot.read_text().split("endheader")[0]
    el = opensim.ExternalLoads(str(xml), True)
    assert el.getSize() == 2 and el.get(0).get_applied_to_body() == "calcn_r"
