"""Gait events and cycles: Zeni events on a synthetic walk, % cycle normalisation, CSV, plots; real trials."""
from __future__ import annotations

import numpy as np
import pytest

from lowerlimb.errors import InputError
from kinematics.gait.gait_cycles import (
    N_POINTS,
    GaitCycle,
    GaitEvent,
    c3d_events,
    cycle_statistics,
    events_from_kinematics,
    events_from_vertical_force,
    gait_cycles,
    normalise_cycle,
    walking_direction,
    write_cycles_csv,
)
from kinematics.io.markers import MarkerTrial


def synthetic_walk(rate=100.0, period=1.0, speed=1.2, treadmill=False, duration=4.0):
    """Pelvis walking along -x (or still, on a treadmill); heel and toe swing sinusoidally about it.

    Relative to the pelvis, the heel is furthest forward at t = k T + phase (foot strike) and the toe
    furthest behind half a period later shifted by 0.1 T (toe off)."""
    t = np.arange(int(duration * rate)) / rate
    d = np.array([-1.0, 0.0, 0.0])
    sac = np.outer((0.0 if treadmill else speed) * t, d) + [0.0, 0.0, 1.0]
    pos, names, truth = [], [], {}
    for s, phase, lat in (("R", 0.25, -0.1), ("L", 0.75, 0.1)):
        heel = sac + np.outer(0.35 * np.cos(2 * np.pi * (t - phase) / period), d) + [0, lat, -0.9]
        toe = sac + np.outer(0.35 * np.cos(2 * np.pi * (t - phase - 0.1 * period) / period) + 0.2, d) + [0, lat, -0.95]
        names += [f"{s}HEE", f"{s}TOE"]
        pos += [heel, toe]
        truth[s] = (phase, phase + 0.6 * period)
    names.append("SACR")
    pos.append(sac)
    return MarkerTrial(tuple(names), np.stack(pos, 1), rate, t, "synthetic walk"), truth


@pytest.mark.parametrize("treadmill", [False, True])
def test_zeni_events_on_a_synthetic_walk(treadmill):
    trial, truth = synthetic_walk(treadmill=treadmill)
    if treadmill:
        # on a treadmill the heel moves forward fast in swing and back slowly in stance
        rate, t = trial.rate, trial.time
        pos = trial.positions.copy()
        for i, s in enumerate("RL"):
            phase = truth[s][0]
            u = ((t - phase) % 1.0)
            rel = np.where(u < 0.6, 0.35 - 0.7 * u / 0.6, -0.35 + 0.7 * (u - 0.6) / 0.4)
            pos[:, 2 * i, 0] = -rel
        trial = MarkerTrial(trial.names, pos, rate, t, "treadmill")
    np.testing.assert_allclose(walking_direction(trial), [-1, 0, 0], atol=1e-9)
    ev = events_from_kinematics(trial)   # Zeni: heel/toe relative to the pelvis, so a treadmill is no different
    for s in "RL":
        strikes = np.array([e.time for e in ev if e.side == s and e.kind == "strike"])
        offs = np.array([e.time for e in ev if e.side == s and e.kind == "off"])
        assert len(strikes) >= 3 and len(offs) >= 3
        np.testing.assert_allclose((strikes - truth[s][0]) % 1.0, 0.0, atol=0.011)  # within a frame
        np.testing.assert_allclose((offs - truth[s][1]) % 1.0, 0.0, atol=0.011)
        cyc = gait_cycles(ev, s)
        # a missed strike would join two strides into one "cycle": such a pair is left out
        missed = [e for e in ev if not (e.side == s and e.kind == "strike" and abs(e.time - strikes[1]) < 1e-9)]
        assert len(gait_cycles(missed, s)) == len(cyc) - 2
        assert all(abs(c.end.time - c.start.time - 1.0) < 0.02 for c in cyc)
        assert all(c.off is not None and abs(c.stance_percent - 60.0) < 2.0 for c in cyc)


def test_standing_trial_has_no_walking_direction():
    trial, _ = synthetic_walk(treadmill=True)
    still = MarkerTrial(("SACR",), trial.positions[:, -1:], trial.rate, trial.time, "standing.c3d")
    with pytest.raises(InputError, match="standing.c3d: the pelvis does not travel"):
        walking_direction(still)


def _cycle(t0, t1, off=None):
    mk = lambda k, t: GaitEvent("R", k, int(t * 100), t, "test")
    return GaitCycle("R", mk("strike", t0), mk("strike", t1), None if off is None else mk("off", off))


def test_normalisation_and_statistics():
    t = np.arange(300) / 100.0
    sig = np.stack([t, 2 * t], -1)
    c1, c2 = _cycle(0.2, 1.2, 0.8), _cycle(1.2, 2.4, 1.92)
    n1 = normalise_cycle(sig, t, c1)
    np.testing.assert_allclose(n1[:, 0], np.linspace(0.2, 1.2, N_POINTS), atol=1e-12)
    st = cycle_statistics(sig, t, [c1, c2])
    np.testing.assert_allclose(st.mean[:, 0], (np.linspace(0.2, 1.2, 101) + np.linspace(1.2, 2.4, 101)) / 2)
    np.testing.assert_allclose(st.sd[:, 1], np.std([2 * np.linspace(0.2, 1.2, 101), 2 * np.linspace(1.2, 2.4, 101)],
                                                   axis=0, ddof=1), atol=1e-12)
    np.testing.assert_allclose(st.stance_percent, [60.0, 60.0], atol=1e-9)
    # a gap inside a cycle is not bridged by the interpolation
    gappy = sig.copy()
    gappy[50:53] = np.nan
    n = normalise_cycle(gappy, t, c1)
    assert np.isnan(n[30, 0]) and np.isfinite(n[:28, 0]).all() and np.isfinite(n[34:, 0]).all()
    with pytest.raises(InputError, match="no complete gait cycle"):
        cycle_statistics(sig, t, [])


def test_vertical_force_events():
    t = np.arange(100) / 100.0
    fz = np.where((t >= 0.2) & (t < 0.75), 600.0, 3.0)
    ev = events_from_vertical_force(t, fz, "L")
    assert [(e.kind, e.frame) for e in ev] == [("strike", 20), ("off", 75)]


def test_csv_and_plots(tmp_path):
    from personalize.presentation.gait_plots import plot_gait_grid

    t = np.arange(300) / 100.0
    cyc = [_cycle(0.2, 1.2, 0.8), _cycle(1.2, 2.4, 1.92)]
    stats = {(f"{j}_angle", s): cycle_statistics(np.stack([np.sin(t), np.cos(t), t], -1), t, cyc)
             for j in ("hip", "knee", "ankle") for s in "RL"}
    p = write_cycles_csv(tmp_path / "c.csv", stats, {"angles": "deg"})
    lines = p.read_text().splitlines()
    assert lines[0].startswith("#") and "deg" in lines[0]
    assert lines[1].split(",")[:3] == ["percent_cycle", "ankle_angle_L_x_mean", "ankle_angle_L_x_sd"]
    assert len(lines) == 2 + N_POINTS
    row = lines[2 + 50].split(",")
    assert float(row[0]) == 50.0 and abs(float(row[1]) - stats[("ankle_angle", "L")].mean[50, 0]) < 1e-5
    img = plot_gait_grid(tmp_path / "angles.png", stats, "angle", "deg")
    assert img.stat().st_size > 10_000


# --------------------------------------------------------------------------- real trials


def test_mocap_pig_strikes_from_plates_and_kinematics(shared_data):
    """Stair descent over four plates: plate events exact; Zeni's (level-walking) kinematic strikes come
    0.09-0.13 s early (the fore foot lands first on a step), toe offs 0.04 s early; no EVENT group stored."""
    from kinematics.io.c3d import read_c3d
    from kinematics.gait.plate_contacts import assign_feet
    from kinematics.io.forceplates import read_force_plates
    from kinematics.gait.gait_cycles import events_from_plates

    path = shared_data / "mocap_pig" / "Movement_trial.c3d"
    trial = read_c3d(path)
    plates = read_force_plates(path)
    ev = events_from_plates(plates, assign_feet(plates, trial))
    assert [(e.side, e.kind, e.frame) for e in ev] == [
        ("R", "strike", 42), ("L", "strike", 105), ("R", "off", 126), ("R", "strike", 166), ("L", "off", 187),
        ("L", "strike", 230), ("R", "off", 252)]
    kin = events_from_kinematics(trial)
    for e in ev:
        near = min((k for k in kin if k.side == e.side and k.kind == e.kind), key=lambda k: abs(k.time - e.time))
        lo, hi = (-0.14, -0.08) if e.kind == "strike" else (-0.06, -0.02)
        assert lo <= near.time - e.time <= hi, (e, near)
    assert c3d_events(path) == []
    assert [(c.start.frame, c.off.frame, c.end.frame) for c in gait_cycles(ev, "R")] == [(42, 126, 166)]


def test_c3d_events_of_a_cropped_trial(tmp_path):
    """Nexus' EVENT group on a trial whose first frame is 100 (1-based): times in read_c3d's time base,
    frames 0-based in the trial; a group with fewer TIMES than USED is refused naming the file."""
    import ezc3d

    from kinematics.io.c3d import read_c3d, write_c3d

    trial = MarkerTrial(("A",), np.ones((50, 1, 3)), 100.0, np.arange(50) / 100.0, "cropped")
    write_c3d(tmp_path / "t.c3d", trial)
    c = ezc3d.c3d(str(tmp_path / "t.c3d"))
    c["header"]["points"]["first_frame"] = 99          # ezc3d's 0-based first frame
    c.add_parameter("EVENT", "USED", [3])
    c.add_parameter("EVENT", "CONTEXTS", ["Right", "Left", "General"])
    c.add_parameter("EVENT", "LABELS", ["Foot Strike", "Foot Off", "Event"])
    c.add_parameter("EVENT", "TIMES", np.array([[0.0, 0.0, 0.0], [1.10, 1.30, 1.2]]))
    c.write(str(tmp_path / "ev.c3d"))
    read = read_c3d(tmp_path / "ev.c3d")
    ev = c3d_events(tmp_path / "ev.c3d")
    assert [(e.side, e.kind, e.frame) for e in ev] == [("R", "strike", 11), ("L", "off", 31)]
    for e in ev:
        assert abs(read.time[e.frame] - e.time) < 1e-6
    c.add_parameter("EVENT", "USED", [5])
    c.write(str(tmp_path / "bad.c3d"))
    with pytest.raises(InputError, match=r"bad\.c3d: EVENT:USED is 5"):
        c3d_events(tmp_path / "bad.c3d")


def test_treadmill_walk_zeni_matches_ground_reactions(shared_data):
    """subject01_walk1 (level treadmill walk, 60 Hz): every Zeni event within 0.035 s of the 20 N GRF event."""
    from kinematics.io.storage import read_mot, read_trc

    d = shared_data / "opensim_gait2392"
    trial = read_trc(d / "subject01_walk1.trc")
    grf = read_mot(d / "subject01_walk1_grf.mot")
    cols = list(grf.columns)
    ref = []
    for side, prefix in (("R", ""), ("L", "1_")):
        ref += events_from_vertical_force(grf.time, grf.values[:, cols.index(prefix + "ground_force_vy")], side)
    kin = events_from_kinematics(trial, heel="{s}.Heel", toe="{s}.Toe.Tip", sacrum="V.Sacral", up=(0, 1, 0))
    inside = [e for e in ref if trial.time[0] + 0.15 < e.time < trial.time[-1] - 0.15]  # a peak needs both sides
    assert len(inside) >= 6
    for e in inside:
        near = min((k for k in kin if k.side == e.side and k.kind == e.kind), key=lambda k: abs(k.time - e.time))
        assert abs(near.time - e.time) < 0.035, (e, near)
