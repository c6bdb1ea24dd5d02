"""TRC / MOT / STO readers and writers: round trips, real OpenSim files, bad input."""
from __future__ import annotations

import numpy as np
import pytest

from lowerlimb.errors import InputError
from kinematics.io.markers import MarkerTrial
from kinematics.io.storage import (Table, guess_rotational, read_mot, read_sto, read_trc, write_mot, write_sto,
                                write_trc)


def _trial(F=7, M=3, seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.normal(0.0, 0.4, (F, M, 3))
    pos[2, 1] = np.nan  # a gap
    pos[F - 1, M - 1] = np.nan  # a trailing gap
    return MarkerTrial(tuple(f"M{j}" for j in range(M)), pos, 100.0, np.arange(F) / 100.0, "synthetic")


@pytest.mark.parametrize("units, tol", [("mm", 1e-9), ("m", 1e-9), ("cm", 1e-9)])
def test_trc_round_trip(tmp_path, units, tol):
    tr = _trial()
    p = write_trc(tmp_path / "a.trc", tr, units=units)
    back = read_trc(p)
    assert back.names == tr.names
    assert back.rate == 100.0
    assert back.extra["units"] == units
    np.testing.assert_allclose(back.time, tr.time, atol=1e-9)
    assert np.array_equal(np.isnan(back.positions), np.isnan(tr.positions))
    ok = ~np.isnan(tr.positions)
    np.testing.assert_allclose(back.positions[ok], tr.positions[ok], atol=tol)
    # The file really is in the requested unit.
    row = (tmp_path / "a.trc").read_text().splitlines()[6].split("\t")
    scale = {"mm": 1e3, "cm": 1e2, "m": 1.0}[units]
    assert float(row[2]) == pytest.approx(tr.positions[0, 0, 0] * scale, abs=1e-5)


def test_trc_opensim_reads_our_file(tmp_path, opensim):
    tr = _trial(F=5, M=2)
    p = write_trc(tmp_path / "b.trc", tr, units="mm")
    t = opensim.TimeSeriesTableVec3(str(p))
    assert t.getNumRows() == 5 and t.getNumColumns() == 2
    assert t.getTableMetaDataAsString("Units") == "mm"
    assert t.getRowAtIndex(0)[0].get(0) == pytest.approx(tr.positions[0, 0, 0] * 1e3, abs=1e-5)
    assert np.isnan(t.getRowAtIndex(4)[1].get(2))  # trailing gap read as NaN


def test_read_real_walk_trc(shared_data):
    tr = read_trc(shared_data / "opensim_gait2392" / "subject01_walk1.trc")
    assert len(tr.names) == 41 and tr.n_frames == 151 and tr.rate == 60.0
    assert tr.names[0] == "R.ASIS"
    # First value of the file is 617.247620 mm.
    assert tr.positions[0, 0, 0] == pytest.approx(0.61724762, abs=1e-9)
    assert tr.time[1] == pytest.approx(0.017)
    # Pelvis markers about 1 m above the floor: the unit conversion worked.
    assert 0.8 < np.nanmean(tr.marker("R.ASIS")[:, 1]) < 1.2


def test_read_real_walk_trc_matches_opensim(shared_data, opensim):
    p = shared_data / "opensim_gait2392" / "subject01_walk1.trc"
    ours = read_trc(p)
    t = opensim.TimeSeriesTableVec3(str(p))
    j = ours.index("L.Heel")
    row = t.getRowAtIndex(100)
    col = list(t.getColumnLabels()).index("L.Heel")
    vec = row[col]
    np.testing.assert_allclose(ours.positions[100, j], [vec.get(k) / 1000.0 for k in range(3)], atol=1e-9)


def test_read_real_knee_trc_and_sto(shared_data):
    tr = read_trc(shared_data / "knee_fluoroscopy" / "DM_ngait_og1.trc")
    assert tr.n_frames == 381 and len(tr.names) == 68 and tr.rate == 120.0
    assert tr.time[0] == pytest.approx(0.75)
    tab = read_sto(shared_data / "knee_fluoroscopy" / "DM_fluoroscopic_gait_knee6dof.sto")
    assert tab.columns == ("knee_ant_r", "knee_sup_r", "knee_lat_r", "knee_flex_r", "knee_add_r", "knee_rot_r")
    assert tab.n_frames == 101 and not tab.in_degrees
    assert tab.time[0] == 0 and tab.time[-1] == 100
    assert tab.column("knee_sup_r")[0] == pytest.approx(0.0417)
    # The column with the ~48 degree range is the one labelled knee_rot_r (see data README).
    rng = np.degrees(np.ptp(tab.column("knee_rot_r")))
    assert 40 < rng < 60
    assert guess_rotational(tab.columns) == {"knee_flex_r", "knee_add_r", "knee_rot_r"}


def test_read_real_ik_mot(shared_data, opensim):
    p = shared_data / "opensim_gait2392" / "subject01_walk1_ik.mot"
    tab = read_mot(p)
    assert tab.in_degrees and tab.n_frames == 211 and len(tab.columns) == 23
    assert tab.header["name"] == "Coordinates"
    assert tab.column("pelvis_tilt")[0] == pytest.approx(4.76281529)
    rad = tab.to_radians(guess_rotational(tab.columns))
    assert not rad.in_degrees
    assert rad.column("pelvis_tilt")[0] == pytest.approx(np.radians(4.76281529))
    assert rad.column("pelvis_tx")[0] == pytest.approx(0.58952689)  # translation untouched
    ref = opensim.TimeSeriesTable(str(p))
    assert ref.getDependentColumn("knee_angle_r").to_numpy()[50] == pytest.approx(tab.column("knee_angle_r")[50])


def test_mot_round_trip_degrees(tmp_path, opensim):
    names = ["hip_flexion_r", "knee_angle_r", "pelvis_tx"]
    t = np.linspace(0, 1, 11)
    vals = np.column_stack([0.5 * np.sin(t), -0.3 * t, 0.2 + t])
    p = write_mot(tmp_path / "c.mot", names, t, vals, in_degrees=True, rotational={"hip_flexion_r", "knee_angle_r"})
    tab = read_mot(p)
    assert tab.in_degrees
    np.testing.assert_allclose(tab.column("knee_angle_r"), np.degrees(-0.3 * t), atol=1e-7)
    np.testing.assert_allclose(tab.column("pelvis_tx"), 0.2 + t, atol=1e-9)
    si = tab.to_radians({"hip_flexion_r", "knee_angle_r"})
    np.testing.assert_allclose(si.values, vals, atol=1e-9)
    # OpenSim agrees on what we wrote.
    ref = opensim.TimeSeriesTable(str(p))
    assert ref.getTableMetaDataAsString("inDegrees") == "yes"
    np.testing.assert_allclose(ref.getDependentColumn("hip_flexion_r").to_numpy(), np.degrees(vals[:, 0]), atol=1e-7)


def test_sto_round_trip_with_header(tmp_path, opensim):
    names = ["a", "b"]
    t = np.arange(4) * 0.01
    vals = np.arange(8.0).reshape(4, 2) / 3.0
    p = write_sto(tmp_path / "d.sto", names, t, vals, header_extra={"frame": "tibia_r", "units": "m"})
    tab = read_sto(p)
    assert tab.header["frame"] == "tibia_r" and tab.header["units"] == "m"
    assert not tab.in_degrees
    np.testing.assert_allclose(tab.values, vals, rtol=1e-9)
    ref = opensim.TimeSeriesTable(str(p))
    np.testing.assert_allclose(ref.getDependentColumn("b").to_numpy(), vals[:, 1], rtol=1e-9)


def test_write_mot_needs_rotational_set(tmp_path):
    with pytest.raises(ValueError):
        write_mot(tmp_path / "e.mot", ["a"], [0.0], [[1.0]], in_degrees=True)
    with pytest.raises(InputError, match="not among"):
        write_mot(tmp_path / "e.mot", ["a"], [0.0], [[1.0]], rotational={"b"})
    assert not (tmp_path / "e.mot").exists()


def test_table_accessors():
    tab = Table(("x", "y"), np.arange(3.0), np.ones((3, 2)), source="t")
    with pytest.raises(InputError, match="'z' is missing"):
        tab.column("z")
    with pytest.raises(InputError, match="missing columns: z, w"):
        tab.select(["x", "z", "w"])
    with pytest.raises(InputError, match="shape"):
        Table(("x",), np.arange(3.0), np.ones((3, 2)))


BAD_TRC = {
    "units": ("PathFileType\t4\t(X/Y/Z)\tx\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n100\t100\t1\t1\tinch\n"
              "Frame#\tTime\tA\t\t\n\t\tX1\tY1\tZ1\n\n1\t0\t1\t2\t3\n", "Units 'inch' unknown"),
    "nframes": ("PathFileType\t4\t(X/Y/Z)\tx\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n100\t100\t3\t1\tmm\n"
                "Frame#\tTime\tA\t\t\n\t\tX1\tY1\tZ1\n\n1\t0\t1\t2\t3\n", "says 3 frames"),
    "nmarkers": ("PathFileType\t4\t(X/Y/Z)\tx\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n100\t100\t1\t2\tmm\n"
                 "Frame#\tTime\tA\t\t\n\t\tX1\tY1\tZ1\n\n1\t0\t1\t2\t3\n", "says 2 markers"),
    "number": ("PathFileType\t4\t(X/Y/Z)\tx\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n100\t100\t1\t1\tmm\n"
               "Frame#\tTime\tA\t\t\n\t\tX1\tY1\tZ1\n\n1\t0\t1\tabc\t3\n", "'abc' is not a number"),
    "long": ("PathFileType\t4\t(X/Y/Z)\tx\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n100\t100\t1\t1\tmm\n"
             "Frame#\tTime\tA\t\t\n\t\tX1\tY1\tZ1\n\n1\t0\t1\t2\t3\t4\n", "more than"),
    "notrc": ("hello\n" * 6, "not a TRC"),
    "short": ("PathFileType\t4\n", "header lines are missing"),
}


@pytest.mark.parametrize("case", sorted(BAD_TRC))
def test_bad_trc(tmp_path, case):
    text, msg = BAD_TRC[case]
    p = tmp_path / "bad.trc"
    p.write_text(text)
    with pytest.raises(InputError, match=msg) as ei:
        read_trc(p)
    assert ei.value.source == str(p)


def test_trc_gaps_and_trailing_fields_dropped(tmp_path):
    # Missing trailing fields = gap; a half-empty triplet is a gap too.
    text = ("PathFileType\t4\t(X/Y/Z)\tx\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n50\t50\t2\t2\tm\n"
            "Frame#\tTime\tA\t\t\tB\t\t\n\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n\n1\t0\t1\t2\t3\n2\t0.02\t1\t\t3\t4\t5\t6\n")
    p = tmp_path / "g.trc"
    p.write_text(text)
    tr = read_trc(p)
    assert np.isnan(tr.positions[0, 1]).all()
    assert np.isnan(tr.positions[1, 0]).all()
    np.testing.assert_allclose(tr.positions[1, 1], [4, 5, 6])


BAD_TABLE = {
    "noend": ("name\nversion=1\ntime\ta\n0\t1\n", "no 'endheader'"),
    "notime": ("name\nendheader\nt\ta\n0\t1\n", "first column label must be 'time'"),
    "ragged": ("name\nendheader\ntime\ta\tb\n0\t1\n", "2 values for 3 column labels"),
    "nrows": ("name\nnRows=5\nendheader\ntime\ta\n0\t1\n", "nRows=5"),
    "deg": ("name\ninDegrees=maybe\nendheader\ntime\ta\n0\t1\n", "yes or no"),
    "nodata": ("name\nendheader\ntime\ta\n", "no data rows"),
    "backwards": ("name\nendheader\ntime\ta\n1\t1\n0\t2\n", "time decreases"),
    "dup": ("name\nendheader\ntime\ta\ta\n0\t1\t2\n", "duplicate column"),
}


@pytest.mark.parametrize("case", sorted(BAD_TABLE))
def test_bad_tables(tmp_path, case):
    text, msg = BAD_TABLE[case]
    p = tmp_path / "bad.sto"
    p.write_text(text)
    with pytest.raises(InputError, match=msg):
        read_sto(p)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        read_mot(tmp_path / "nope.mot")


def test_trc_unit_spelled_out(tmp_path):
    text = ("PathFileType\t4\t(X/Y/Z)\tx\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n100\t100\t1\t1\tMillimeters\n"
            "Frame#\tTime\tA\t\t\n\t\tX1\tY1\tZ1\n\n1\t0\t1000\t2\t3\n")
    p = tmp_path / "u.trc"
    p.write_text(text)
    tr = read_trc(p)
    assert tr.extra["units"] == "mm"
    np.testing.assert_allclose(tr.positions[0, 0], [1.0, 0.002, 0.003])
