"""The run's OpenSim set-ups run in OpenSim as written: IK, inverse dynamics and static optimisation (reserve
actuators) of a trial with force plates, compared with personalize's own inverse dynamics.

Subject: the ICL-MRI real-anatomy phantom (shared data) walking over two force plates (`phantoms.force_plates`),
Plug-in-Gait markers, Z-up lab; its bones are a mesh folder.  Measured (seed 4): pipeline 60 s; OpenSim's
InverseDynamicsTool on ``gait_01_id_setup.xml`` within 4e-10 of each column's peak of
`personalize.joint_dynamics.trial_joint_dynamics` on the same files; the static optimisation's reserves and
residuals within 0.025 N m / N of the ID generalised forces (the knee rotations' reserves carry the coupled knee
translations' forces too: the coupler constraints' work, reserve = tau_rot + Sᵀ tau_trans, S the knee law's
slopes).  Without the shared data, the set-up writers are checked on the demo phantom's model with a synthetic
ground reaction (`test_setup_writers_on_the_demo_model`, in test_pipeline.py's demo module).
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from kinematics.io.storage import read_sto
from opensim_checks import ID_ABS_TOL, ID_REL_TOL, check_so_reproduces_id, generalised_force



@pytest.fixture(scope="module")
def fp_run(shared_data, tmp_path_factory, opensim):
    from phantoms.real_anatomy import load_real_anatomy
    from phantoms.real_subject import write_real_subject
    from personalize.pipeline import run_subject

    anat = load_real_anatomy(shared_data / "bones" / "ICL_MRI", shared_data / "reference_models" / "manual_ICL_MRI.osim")
    root = tmp_path_factory.mktemp("force_plates")
    subj = root / "subject"
    subj.mkdir()
    write_real_subject(subj, anat, marker_set="pig", lab="z-up", walk="+x", build="adult", seed=4, labels=False,
                       meshes=True, mesh_folder="bones", functional=False, static_frames=20, gait_trials=1,
                       force_plates=True)
    out = root / "out"
    return out, run_subject(subj, out, report=False)


def _quiet(opensim):
    opensim.Logger.setLevelString("warn")


def test_setups_written_with_units_and_loads(fp_run):
    out, summary = fp_run
    ds = summary["dynamics_setups"]
    assert set(ds) == {"gait_01"}
    g = ds["gait_01"]
    assert g["loaded_bodies"] == ["calcn_r", "calcn_l"]
    t0, t1 = g["time_range_s"]
    assert t1 - t0 > 1.0                              # the stretch with every ground reaction known
    for f in g["files"].values():
        assert (out / f).is_file(), f
    head = (out / "kinematics" / "gait_01_grf.mot").read_text().split("endheader")[0]
    assert "force N, point (centre of pressure) m, torque (free moment about the point) N m" in head
    assert "model's ground" in head
    for f in ("gait_01_id_setup.xml", "gait_01_so_setup.xml"):
        assert "N m" in (out / "kinematics" / f).read_text().split("<OpenSimDocument")[0]
    # the model's ground: Y up, the vertical reaction about body weight while a foot is on a plate
    grf = read_sto(out / "kinematics" / "gait_01_grf.mot")
    fy = grf.values[:, grf.columns.index("ground_force_vy")] + grf.values[:, grf.columns.index("1_ground_force_vy")]
    bw = json.loads((out.parent / "subject" / "subject.json").read_text())["mass"] * 9.80665
    assert 0.9 * bw < np.nanmax(fy) < 1.6 * bw and np.nanmin(fy) > -1.0


def test_opensim_runs_the_setups_as_written(fp_run, opensim):
    """IK (static), ID and SO set-ups run by OpenSim's tools unedited; ID = personalize's ID; SO = ID."""
    from kinematics.io.dynamics_setup import run_setup
    from personalize.joint_dynamics import trial_joint_dynamics

    out, summary = fp_run
    _quiet(opensim)
    k = out / "kinematics"
    assert run_setup(k / "static_ik_setup.xml") == "InverseKinematicsTool"
    assert (k / "static_opensim_ik.mot").is_file()
    assert run_setup(k / "gait_01_id_setup.xml") == "InverseDynamicsTool"
    os_id = read_sto(k / "gait_01_opensim_id.sto")
    t0, t1 = summary["dynamics_setups"]["gait_01"]["time_range_s"]
    assert os_id.time[0] == pytest.approx(t0) and os_id.time[-1] == pytest.approx(t1)
    mine = trial_joint_dynamics(out / "model.osim", k / "gait_01.mot", loads=(k / "gait_01_grf.mot", k / "gait_01_grf.xml"),
                                cutoff=6.0, start=t0, end=t1).result
    assert mine.time.shape == os_id.time.shape
    hip = None
    for c in mine.coordinates:
        a, b = generalised_force(os_id, c), mine[c]
        peak = np.abs(a).max()
        assert np.abs(a - b).max() < ID_REL_TOL * peak + ID_ABS_TOL, c
        if c == "hip_flexion_r":
            hip = peak
    assert hip is not None and hip > 30.0             # a real walk's hip moment, not an empty load
    assert run_setup(k / "gait_01_so_setup.xml") == "AnalyzeTool"
    so = read_sto(k / "gait_01_so_StaticOptimization_force.sto")
    diffs = check_so_reproduces_id(json.loads((out / "model.json").read_text()), os_id, so)
    assert {"residual_pelvis_ty", "reserve_knee_flexion_r", "reserve_ankle_angle_l"} <= set(diffs)
    assert not any(a.startswith(("reserve_knee_t", "reserve_mtp")) for a in diffs)   # coupled / locked: no actuator
