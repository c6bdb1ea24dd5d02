"""Checks of OpenSim's tools' results against personalize's (shared by the set-up tests)."""
from __future__ import annotations

import numpy as np

#: OpenSim's ID vs personalize's on the same files: fraction of each column's peak (measured 4e-10), plus the
#: precision of OpenSim's printed values (N m / N)
ID_REL_TOL, ID_ABS_TOL = 1e-6, 1e-6
#: static optimisation vs ID: abs (N m or N) + fraction of the column's peak (measured 0.025 N m, 1.2e-3 of peak)
SO_ABS_TOL, SO_REL_TOL = 0.1, 2e-3


def generalised_force(table, coordinate: str) -> np.ndarray:
    """The ``<coordinate>_moment`` or ``_force`` column of an ID storage."""
    for suffix in ("_moment", "_force"):
        if coordinate + suffix in table.columns:
            return table.values[:, table.columns.index(coordinate + suffix)]
    raise KeyError(coordinate)


def check_so_reproduces_id(model_json: dict, id_table, so_table) -> dict:
    """Every reserve/residual force of the static optimisation against the ID generalised force of its coordinate
    (knee rotations: plus the coupled translations' forces through the knee law); returns actuator -> max |diff|."""
    laws = model_json["knee_laws"]
    coupled = {}
    for law in laws.values():
        C = np.asarray(law["coefficients"], float)[:, :-1]
        for i, c in enumerate(law["independent"]):
            coupled[c] = [(d, C[j, i]) for j, d in enumerate(law["dependent"])]
    diffs = {}
    actuators = [c for c in so_table.columns if c.startswith(("reserve_", "residual_", "reaction_"))]
    assert actuators
    for a in actuators:
        c = a.split("_", 1)[1]
        expected = generalised_force(id_table, c) + sum(s * generalised_force(id_table, d) for d, s in coupled.get(c, ()))
        got = np.interp(id_table.time, so_table.time, so_table.values[:, so_table.columns.index(a)])
        d = float(np.abs(got - expected).max())
        assert d < SO_ABS_TOL + SO_REL_TOL * np.abs(expected).max(), (a, d, np.abs(expected).max())
        diffs[a] = d
    return diffs


def opensim_ik_difference_deg(setup, ours_mot, results_dir, model_file) -> tuple[float, list]:
    """OpenSim's IK tool run on `setup` against personalize's ``.mot`` of the same trial (`model_file`: its model,
    for which columns the file holds in degrees): the largest difference of any rotational coordinate both have
    (deg) and OpenSim's coordinate names."""
    from kinematics.io.opensim_io import degree_coordinates, load_osim, run_opensim_ik_tool
    from kinematics.io.storage import read_mot

    ours = read_mot(ours_mot).to_radians(degree_coordinates(load_osim(model_file)))
    theirs = run_opensim_ik_tool(setup, results_dir)
    worst = 0.0
    for i, c in enumerate(theirs["coordinates"]):
        if c in ours.columns and not c.endswith(("_tx", "_ty", "_tz")):
            q = np.interp(ours.time, theirs["time"], theirs["q"][:, i])
            worst = max(worst, float(np.degrees(np.nanmax(np.abs(ours.values[:, ours.columns.index(c)] - q)))))
    return worst, list(theirs["coordinates"])


def synthetic_load_id_against_opensim(model_dir, tmp_path, trial: str = "gait_01"):
    """A run's model and gait IK with a synthetic ground reaction on calcn_r: OpenSim's ID (its set-up as the
    writers write it) against personalize's on the same files, every coordinate within `ID_REL_TOL` of its peak
    plus `ID_ABS_TOL`.  Returns (folder, OpenSim's ID table, ID window, common set-up arguments)."""
    import shutil

    from kinematics.io.dynamics_setup import run_setup, write_id_setup
    from kinematics.io.external_loads import ExternalLoad, write_external_loads
    from kinematics.io.storage import read_mot, read_sto
    from personalize.joint_dynamics import trial_joint_dynamics

    shutil.copy(model_dir / "model.osim", tmp_path / "model.osim")
    shutil.copy(model_dir / "model.json", tmp_path / "model.json")
    k = tmp_path / "kinematics"
    k.mkdir()
    shutil.copy(model_dir / "kinematics" / f"{trial}.mot", k / f"{trial}.mot")
    mot = read_mot(k / f"{trial}.mot")
    t = mot.time
    x = lambda c: mot.values[:, mot.columns.index(c)]  # noqa: E731
    w = 2 * np.pi * t
    F = np.column_stack([30 * np.sin(w), 700 + 100 * np.sin(2 * w), 10 * np.cos(w)])        # N, ground
    P = np.column_stack([x("pelvis_tx"), np.zeros_like(t), x("pelvis_tz")])                  # m, under the pelvis
    T = np.column_stack([np.zeros_like(t), 2 * np.cos(w), np.zeros_like(t)])                 # N m
    write_external_loads(k, f"{trial}_grf", [ExternalLoad("R_ground_reaction", "calcn_r", t, F, P, T)],
                         frame="model ground")
    window = (float(t[5]), float(t[-6]))
    common = dict(model_file="../model.osim", coordinates_file=f"{trial}.mot", external_loads_file=f"{trial}_grf.xml",
                  time_range=window, cutoff_hz=6.0)
    write_id_setup(k / "id.xml", output_gen_force_file="id.sto", name=f"{trial}_id", **common)
    assert run_setup(k / "id.xml") == "InverseDynamicsTool"
    os_id = read_sto(k / "id.sto")
    mine = trial_joint_dynamics(tmp_path / "model.osim", k / f"{trial}.mot",
                                loads=(k / f"{trial}_grf.mot", k / f"{trial}_grf.xml"), cutoff=6.0,
                                start=window[0], end=window[1]).result
    assert mine.time.shape == os_id.time.shape
    for c in mine.coordinates:
        a = generalised_force(os_id, c)
        assert np.abs(a - mine[c]).max() < ID_REL_TOL * np.abs(a).max() + ID_ABS_TOL, c
    return k, os_id, common
