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


def opensim_ik_difference_deg(setup, ours_mot, results_dir) -> tuple[float, list]:
    """OpenSim's IK tool run on `setup` against personalize's ``.mot`` of the same trial: the largest difference of
    any rotational coordinate both have (deg) and OpenSim's coordinate names."""
    from kinematics.io.opensim_io import run_opensim_ik_tool
    from kinematics.io.storage import read_mot

    ours = read_mot(ours_mot)
    theirs = run_opensim_ik_tool(setup, results_dir)
    worst = 0.0
    for i, c in enumerate(theirs["coordinates"]):
        if c in ours.columns and not c.endswith(("_tx", "_ty", "_tz")):
            q = np.interp(ours.time, theirs["time"], np.degrees(theirs["q"][:, i]))
            worst = max(worst, float(np.nanmax(np.abs(ours.values[:, ours.columns.index(c)] - q))))
    return worst, list(theirs["coordinates"])
