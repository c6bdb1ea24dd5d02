"""The kinematics of every trial on the personalised model: IK and the blended hip-first / foot-first chains."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lowerlimb.atomic import inside
from lowerlimb.errors import FitError, InputError

from .inputs import SubjectInputs

__all__ = ["TrialFit", "solve_trials", "chain_blend", "OPENSIM_IK_ACCURACY"]

#: accuracy of the written OpenSim IK setups: OpenSim's default 1e-5 stops its assembler early (phantom gait: marker
#: RMS up to 0.05 mm above the optimum, the weakly determined subtalar angle up to 2.4 deg away); at 1e-8 it lands
#: on personalize's solution (within 0.005 deg)
OPENSIM_IK_ACCURACY = 1e-8


@dataclass(frozen=True)
class TrialFit:
    """IK marker residuals of one trial (summary.json ``ik``)."""

    rms_mean_mm: float
    rms_max_mm: float
    frames: int
    worst_marker: str

    def summary(self) -> dict:
        return {"rms_mean_mm": self.rms_mean_mm, "rms_max_mm": self.rms_max_mm, "frames": self.frames,
                "worst_marker": self.worst_marker}


def solve_trials(pm, inputs: SubjectInputs, stage: Path, say, notes: list | None = None) -> tuple[dict, dict]:
    """IK (`kinematics.algorithms.ik.solve_ik`) of the static and every motion trial on the model `pm`.

    The trials (internal frame) are mapped into the model's ground (`personalize.model_builder.trial_in_ground`).
    Writes into `stage`, per trial:

    * ``kinematics/<trial>.mot``: coordinates (rotations in deg);
    * ``kinematics/<trial>_marker_errors.sto`` (`personalize.inverse_kinematics.write_marker_errors`: OpenSim's
      columns, then per marker, m);
    * ``kinematics/<trial>.trc``: the markers in the model's ground (mm), and ``kinematics/<trial>_ik_setup.xml``,
      an OpenSim IK setup of the same problem (``../model.osim``, every tracked marker with weight 1 as
      ``solve_ik`` weighs them, the trial's time range, accuracy `OPENSIM_IK_ACCURACY`, output
      ``<trial>_opensim_ik.mot``), so that OpenSim's IK tool reproduces the ``.mot``.

    `notes`, when given, receives the coordinates the markers leave undetermined (per trial) and the locked ones.
    Returns (trial -> IK result, trial -> `TrialFit`).
    """
    from kinematics.algorithms.ik import solve_ik
    from kinematics.io.ik_setup import write_ik_setup
    from kinematics.io.storage import write_mot, write_trc

    from ..inverse_kinematics import write_marker_errors
    from ..model_builder import trial_in_ground

    from kinematics.io.opensim_io import degree_coordinates

    results, fits = {}, {}
    in_degrees = degree_coordinates(pm.model)        # a patella's coupled coordinate stays in radians, as OpenSim reads it
    locked = [c.name for c in pm.model.coordinates if c.locked]
    if notes is not None and locked:
        notes.append(f"IK: {', '.join(locked)} locked at the standing pose (no marker on the distal body)")
    for name in ["static"] + sorted(inputs.trials):
        trial = trial_in_ground(pm, inputs.static if name == "static" else inputs.trials[name])
        say(f"IK {name}")
        res = solve_ik(pm.model, trial)
        results[name] = res
        write_mot(inside(stage, f"kinematics/{name}.mot"), pm.model.coordinate_names, res.time, res.q,
                  rotational=in_degrees, name=f"IK {name}")
        write_marker_errors(inside(stage, f"kinematics/{name}_marker_errors.sto"), res, header=[f"IK {name}"])
        write_trc(inside(stage, f"kinematics/{name}.trc"), trial.subset(res.markers), units="mm")
        write_ik_setup(inside(stage, f"kinematics/{name}_ik_setup.xml"), model_file="../model.osim",
                       marker_file=f"{name}.trc", output_motion_file=f"{name}_opensim_ik.mot",
                       marker_weights={m: 1.0 for m in res.markers},
                       time_range=(float(res.time[0]), float(res.time[-1])), accuracy=OPENSIM_IK_ACCURACY,
                       name=f"{name}_ik")
        me = np.nanmean(res.marker_errors, axis=0)
        fits[name] = TrialFit(float(np.nanmean(res.rms) * 1e3), float(np.nanmax(res.rms) * 1e3), int(res.q.shape[0]),
                              f"{res.markers[int(np.nanargmax(me))]} {np.nanmax(me) * 1e3:.1f} mm")
        if notes is not None and res.undetermined_coordinates:
            n_und = int((res.solved & ~res.determined).sum())
            notes.append(f"IK {name}: the markers do not determine {', '.join(res.undetermined_coordinates)} in "
                         f"{n_und} of {res.q.shape[0]} frames (kept at the previous frame's value there)")
    return results, fits


def chain_blend(inputs: SubjectInputs, stage: Path, notes: list) -> tuple[dict, dict]:
    """Per-frame Gaussian blend of the hip-first and foot-first chains of every dynamic trial (`kinematics.gait.chain_blend`).

    Writes ``kinematics/<trial>_chains.mot`` (Plug-in-Gait angles of the blended segments, deg) and
    ``kinematics/<trial>_chain_weights.sto`` (the foot-to-hip chain's weight per segment); returns the median
    weights (summary.json ``chain_blend``) and trial -> {chain name or "blend": reconstruction}.
    """
    from kinematics.gait.reconstruction import ANGLE_COLUMNS, reconstruct
    from kinematics.io.storage import write_mot, write_sto

    func = inputs.trials.get(inputs.functional) if inputs.functional else None
    out: dict = {"median_foot_to_hip_weight": {}, "files": "kinematics/<trial>_chains.mot (deg), "
                 "kinematics/<trial>_chain_weights.sto (weight of the foot-to-hip chain; Plug-in-Gait has 1 - w)"}
    chains: dict = {}
    for name, trial in sorted(inputs.trials.items()):
        if name == inputs.functional or name.startswith("functional"):
            continue
        try:
            rec = reconstruct(trial, "blend", static=inputs.static, subject=inputs.subject, functional=func,
                              check_static=False)
        except (InputError, FitError) as exc:
            notes.append(f"chain blend of {name}: {exc}")
            continue
        chains[name] = {**rec.chains, "blend": rec}
        write_mot(inside(stage, f"kinematics/{name}_chains.mot"), ANGLE_COLUMNS, rec.time, rec.angle_table(),
                  rotational=ANGLE_COLUMNS, name=f"blended chains {name}")
        segs = sorted(rec.weights)
        write_sto(inside(stage, f"kinematics/{name}_chain_weights.sto"), segs, rec.time,
                  np.column_stack([rec.weights[k] for k in segs]),
                  header_extra=["weight of the foot-to-hip chain per segment and frame (0-1)"], name="ChainWeights")
        out["median_foot_to_hip_weight"][name] = {k: float(np.nanmedian(v)) for k, v in rec.weights.items()
                                                  if np.isfinite(v).any()}
    return out, chains
