"""``personalize ik`` command (personalize/commands/ik.py)."""
from __future__ import annotations

import numpy as np
import pytest

from kin_helpers import leg_model
from kinematics.algorithms.fk import marker_positions
from kinematics.io.markers import MarkerTrial
from kinematics.io.storage import read_mot, read_sto, write_trc
from personalize.cli import main

GAIT = "opensim_gait2392"


@pytest.fixture(scope="module")
def leg_files(tmp_path_factory, opensim):
    from kinematics.io.opensim_io import save_osim

    d = tmp_path_factory.mktemp("cli_ik")
    m = leg_model()
    model_path = save_osim(m, d / "leg.osim")
    t = np.arange(30) / 100.0
    q = np.tile(m.default_q, (len(t), 1))
    q[:, m.coordinate_index("knee_angle")] = -0.2 - 0.6 * t
    q[:, m.coordinate_index("hip_flexion")] = 0.3 * np.sin(3 * t)
    q[:, m.coordinate_index("pelvis_tx")] = 1.2 * t
    x = marker_positions(m, q)
    return m, model_path, t, q, x, d


def _write(d, name, m, x, t, units="mm", names=None):
    path = d / name
    write_trc(path, MarkerTrial(names or m.marker_names, x, 100.0, t, str(path)), units=units)
    return path


def test_cli_ik_writes_mot_in_degrees_and_marker_errors(leg_files, capsys):
    m, model_path, t, q, x, d = leg_files
    trc = _write(d, "walk.trc", m, x, t)
    out = d / "res" / "walk_ik.mot"
    assert main(["ik", str(model_path), str(trc), "--out", str(out), "--start", "0.05", "--end", "0.25", "--quiet"]) == 0
    mot = read_mot(out)
    keep = (t >= 0.05 - 1e-9) & (t <= 0.25 + 1e-9)
    np.testing.assert_allclose(mot.time, t[keep], atol=1e-6)
    vals = mot.values[:, [mot.columns.index(c) for c in m.coordinate_names]]
    rot = m.rotational
    assert mot.in_degrees
    np.testing.assert_allclose(np.radians(vals[:, rot]), q[keep][:, rot], atol=1e-5)
    np.testing.assert_allclose(vals[:, ~rot], q[keep][:, ~rot], atol=1e-5)
    err = read_sto(d / "res" / "walk_ik_marker_errors.sto")
    assert err.columns == ("total_squared_error", "marker_error_RMS", "marker_error_max", *m.marker_names)
    assert err.values[:, 1].max() < 1e-5          # exact synthetic markers (TRC rounding only)
    per = err.values[:, 3:]                       # per marker; OpenSim's columns follow from them
    np.testing.assert_allclose(err.values[:, 0], np.sum(per ** 2, axis=1), rtol=1e-6, atol=1e-18)
    np.testing.assert_allclose(err.values[:, 2], per.max(axis=1), rtol=1e-6, atol=1e-12)


def test_cli_ik_skips_empty_frames_and_solves_gappy_ones(leg_files, capsys):
    m, model_path, t, q, x, d = leg_files
    x = x.copy()
    x[4] = np.nan                                   # every marker missing
    x[5:9, :3] = np.nan                             # three pelvis markers missing in 4 frames
    x[12, 4:] = np.nan                              # only pelvis markers: the leg is undetermined
    trc = _write(d, "gaps.trc", m, x, t)
    out = d / "gaps.mot"
    assert main(["ik", str(model_path), str(trc), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "1 frame(s) with every tracked marker missing" in err
    assert "1 frame(s) have too few markers" in err and "0.1200" in err
    mot = read_mot(out)
    assert len(mot.time) == len(t) - 1 and not np.isclose(mot.time, t[4]).any()
    i = mot.columns.index("knee_angle")
    good = np.delete(np.arange(len(t)), [4, 12])
    np.testing.assert_allclose(np.radians(mot.values[np.searchsorted(mot.time, t[good] - 1e-9), i]),
                               q[good, m.coordinate_index("knee_angle")], atol=1e-5)


def test_cli_ik_bad_inputs(leg_files, tmp_path, capsys):
    m, model_path, t, q, x, d = leg_files
    trc = _write(d, "ok.trc", m, x, t)
    notxml = tmp_path / "model.osim"
    notxml.write_text("hello")
    assert main(["ik", str(notxml), str(trc), "--out", str(tmp_path / "a.mot")]) == 2
    assert "not an OpenSim model" in capsys.readouterr().err
    otrc = _write(tmp_path, "other.trc", m, x[:, :3], t, names=("A", "B", "C"))
    assert main(["ik", str(model_path), str(otrc), "--out", str(tmp_path / "b.mot")]) == 2
    assert "no marker of the model" in capsys.readouterr().err
    # Millimetre values under a header that says metres.
    mm_as_m = _write(tmp_path, "mm_as_m.trc", m, x * 1000.0, t, units="m")
    assert main(["ik", str(model_path), str(mm_as_m), "--out", str(tmp_path / "c.mot")]) == 2
    msg = capsys.readouterr().err
    assert "look like millimetres" in msg and "Units=m" in msg
    empty = _write(tmp_path, "empty.trc", m, np.full_like(x, np.nan), t)
    assert main(["ik", str(model_path), str(empty), "--out", str(tmp_path / "d.mot")]) == 2
    assert "every frame" in capsys.readouterr().err
    assert main(["ik", str(model_path), str(trc), "--out", str(tmp_path / "e.txt")]) == 2
    assert not list(tmp_path.glob("*.mot")) and not list(tmp_path.glob("*.sto"))


def test_cli_ik_with_opensim_setup(shared_data, tmp_path):
    d = shared_data / GAIT
    out = tmp_path / "walk1_ik.mot"
    code = main(["ik", str(d / "subject01_simbody_adjusted.osim"), str(d / "subject01_walk1.trc"), "--out", str(out),
                 "--setup", str(d / "subject01_Setup_IK.xml"), "--start", "0.5", "--end", "0.7", "--quiet"])
    assert code == 0
    mot = read_mot(out)
    assert len(mot.time) == 13 and mot.in_degrees
    ref = read_mot(d / "subject01_walk1_ik.mot")
    # Same coordinates as OpenSim's published result for this walk (to a few degrees; model versions differ).
    k = [int(np.argmin(np.abs(ref.time - s))) for s in mot.time]
    j = mot.columns.index("knee_angle_r")
    assert np.abs(mot.values[:, j] - ref.values[k, ref.columns.index("knee_angle_r")]).max() < 3.0
    err = read_sto(tmp_path / "walk1_ik_marker_errors.sto")
    assert 0.01 < err.values[:, 1].mean() < 0.04


def test_trial_ik_from_a_script(leg_files, tmp_path):
    """The library form of the command: TrialIK holds the solution, write_trial_ik writes both files."""
    from lowerlimb.errors import InputError
    from personalize.inverse_kinematics import trial_inverse_kinematics, write_trial_ik

    m, model_path, t, q, x, d = leg_files
    trc = _write(tmp_path, "walk.trc", m, x, t)
    res = trial_inverse_kinematics(model_path, trc, end=0.1)
    keep = t <= 0.1 + 1e-9
    assert res.solved.sum() == keep.sum() and not res.underdetermined.any() and res.warnings == ()
    rot = m.rotational
    np.testing.assert_allclose(res.ik.q[:, rot], q[keep][:, rot], atol=1e-5)
    assert res.rms_max < 1e-5 and res.coordinates == tuple(m.coordinate_names)
    mot, err = write_trial_ik(res, tmp_path / "w.mot")
    assert err == tmp_path / "w_marker_errors.sto"
    np.testing.assert_allclose(np.radians(read_mot(mot).values[:, rot]), res.ik.q[:, rot], atol=1e-6)
    with pytest.raises(InputError, match="clamped, all or none"):
        trial_inverse_kinematics(model_path, trc, limits="some")


def test_cli_ik_reads_the_lab(shared_data, tmp_path, capsys):
    """opensim_gait2392's walk (Y-up TRC, OpenSim names, walking in place): Y up, facing +X, printed and returned."""
    from personalize.inverse_kinematics import trial_inverse_kinematics

    d = shared_data / GAIT
    model, trc = d / "subject01_simbody_adjusted.osim", d / "subject01_walk1.trc"
    assert main(["ik", str(model), str(trc), "--out", str(tmp_path / "w.mot"), "--start", "0.5", "--end", "0.6"]) == 0
    assert "lab: Y up, facing +X, floor at 0.03" in capsys.readouterr().err
    res = trial_inverse_kinematics(model, trc, start=0.5, end=0.6)
    np.testing.assert_array_equal(res.lab.up, [0, 1, 0])
    # heel-to-toe over a tenth of a stride: 4.6 deg off +X (2.7 deg over the whole trial)
    assert res.lab.forward @ [1, 0, 0] > np.cos(np.radians(10))
    np.testing.assert_allclose(res.lab.rotation_to_opensim @ res.lab.up, [0, 1, 0])


def test_trial_ik_without_a_readable_lab_says_why(leg_files, tmp_path):
    """A leg without pelvis or foot names standing still: no lab, the reason kept, the IK unchanged."""
    from personalize.inverse_kinematics import trial_inverse_kinematics

    m, model_path, t, q, x, d = leg_files
    res = trial_inverse_kinematics(model_path, _write(tmp_path, "walk.trc", m, x, t), end=0.1)
    assert res.lab is None and "walk.trc: cannot tell the feet from the head" in res.lab_problem
    assert res.warnings == () and res.rms_max < 1e-5
