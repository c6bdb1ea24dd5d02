"""Force plates: real C3D (Vicon, four Kistler type-2 plates) against Nexus and ezc3d; modified files for bad input."""
from __future__ import annotations

import numpy as np
import pytest

from lowerlimb.errors import InputError
from kinematics.gait.plate_contacts import assign_feet
from kinematics.io.forceplates import box_average, read_force_plates

MASS_KG = 85.0  # PROCESSING:Bodymass of Movement_trial.c3d


@pytest.fixture(scope="module")
def trial(shared_data):
    return shared_data / "mocap_pig" / "Movement_trial.c3d"


@pytest.fixture(scope="module")
def plates(trial):
    return read_force_plates(trial)


# Modified copies of the trial, written by ezc3d in a child process: once opensim's SWIG module is
# loaded (other test files), ezc3d's own SWIG wrappers refuse the parameter shapes in this process.
_EDITS = r"""
import sys
import numpy as np
import ezc3d

src, out = sys.argv[1], sys.argv[2]

def load():
    return ezc3d.c3d(src)

c = load()  # plate 1 shrunk to 30 % about its centre: its CoPs fall outside
corners = np.array(c["parameters"]["FORCE_PLATFORM"]["CORNERS"]["value"], float)
centre = corners[:, :, 0].mean(axis=1, keepdims=True)
corners[:, :, 0] = centre + 0.3 * (corners[:, :, 0] - centre)
c["parameters"]["FORCE_PLATFORM"]["CORNERS"]["value"] = corners
c.write(out + "/shrunk.c3d")

c = load()  # plate 1 with zero corners, and a NaN sample in plate 2's first channel
corners = np.array(c["parameters"]["FORCE_PLATFORM"]["CORNERS"]["value"], float)
corners[:, :, 0] = 0.0
c["parameters"]["FORCE_PLATFORM"]["CORNERS"]["value"] = corners
c.write(out + "/nocorners.c3d")
c = load()
an = np.array(c["data"]["analogs"], float)
ch = int(np.array(c["parameters"]["FORCE_PLATFORM"]["CHANNEL"]["value"])[0, 1]) - 1
an[0, ch, 500] = np.nan
c["data"]["analogs"] = an
c.write(out + "/nan_analog.c3d")

c = load()  # no force platform
c["parameters"]["FORCE_PLATFORM"]["USED"]["value"] = np.array([0])
c.write(out + "/noplates.c3d")

c = load()  # plate 1 as type 4 with a calibration matrix (gain 2, cross-talk fx' = 2 fx + 0.5 fy)
cal = np.diag([2.0] * 6)
cal[0, 1] = 0.5
c["parameters"]["FORCE_PLATFORM"]["TYPE"]["value"] = np.array([4, 2, 2, 2])
c.add_parameter("FORCE_PLATFORM", "CAL_MATRIX", np.repeat(cal[:, :, None], 4, axis=2))
c.write(out + "/type4.c3d")

c = load()  # type 4 without a calibration matrix
c["parameters"]["FORCE_PLATFORM"]["TYPE"]["value"] = np.array([4, 2, 2, 2])
c.write(out + "/type4_nocal.c3d")

# Plate 1 re-expressed as type 1 (Fx Fy Fz N, CoP x y mm, Tz N mm) and as type 3 (Kistler, 8 channels,
# ORIGIN a b az0): the same wrench, so the reader must find the same force, CoP and free moment.
c = load()
an = np.array(c["data"]["analogs"], float)
f, m_o = an[0, 0:3].T, an[0, 3:6].T                      # plate frame, N and N mm about the sensor origin
o = np.array([0.0, 0.0, -41.0])                          # surface centre from the sensor origin (plate Z down)
Mc = m_o + np.cross(f, o)
fz = f[:, 2]
ok = np.abs(fz) > 5.0
cx = np.where(ok, -Mc[:, 1] / np.where(ok, fz, 1.0), 0.0)
cy = np.where(ok, Mc[:, 0] / np.where(ok, fz, 1.0), 0.0)
tz = np.where(ok, Mc[:, 2] - (cx * f[:, 1] - cy * f[:, 0]), 0.0)
t1 = an.copy()
t1[0, 3], t1[0, 4], t1[0, 5] = cx, cy, tz
c["data"]["analogs"] = t1
units = list(c["parameters"]["ANALOG"]["UNITS"]["value"])
units[3], units[4], units[5] = "mm", "mm", "Nmm"
c["parameters"]["ANALOG"]["UNITS"]["value"] = units
c["parameters"]["FORCE_PLATFORM"]["TYPE"]["value"] = [1, 2, 2, 2]
c.write(out + "/type1.c3d")

c = load()
a, b = 120.0, 200.0
Mz = m_o[:, 2]
fx12, fx34 = f[:, 0] / 2 - Mz / (2 * b), f[:, 0] / 2 + Mz / (2 * b)
fy14 = fy23 = f[:, 1] / 2
A = np.array([[1, 1, 1, 1], [b, b, -b, -b], [-a, a, a, -a], [1, -1, 1, -1]], float)
fz4 = np.linalg.solve(A, np.vstack([f[:, 2], m_o[:, 0], m_o[:, 1], np.zeros(len(f))]))
t3 = an.copy()
t3[0, 0], t3[0, 1], t3[0, 2], t3[0, 3], t3[0, 4], t3[0, 5] = fx12, fx34, fy14, fy23, fz4[0], fz4[1]
t3[0, 24], t3[0, 25] = fz4[2], fz4[3]
c["data"]["analogs"] = t3
units = list(c["parameters"]["ANALOG"]["UNITS"]["value"])
units[3] = units[4] = units[5] = units[24] = units[25] = "N"
c["parameters"]["ANALOG"]["UNITS"]["value"] = units
fp = c["parameters"]["FORCE_PLATFORM"]
ch = np.array(fp["CHANNEL"]["value"], int)
fp["CHANNEL"]["value"] = np.vstack([ch, [[25, 1, 1, 1], [26, 1, 1, 1]]])
org = np.array(fp["ORIGIN"]["value"], float)
org[:, 0] = [a, b, -41.0]
fp["ORIGIN"]["value"] = org
fp["TYPE"]["value"] = [3, 2, 2, 2]
c.write(out + "/type3.c3d")
"""


@pytest.fixture(scope="module")
def modified(trial, tmp_path_factory):
    import subprocess
    import sys

    pytest.importorskip("ezc3d")
    out = tmp_path_factory.mktemp("c3d")
    subprocess.run([sys.executable, "-c", _EDITS, str(trial), str(out)], check=True, capture_output=True)
    return out


def test_four_plates_cop_inside_and_matches_nexus(trial, plates):
    from kinematics.io.c3d import read_c3d_outputs

    assert len(plates) == 4 and plates.rate == 120.0
    assert plates.time.shape == (plates.n_frames,)
    for p in plates:
        assert p.type == 2 and p.force.shape == (plates.n_frames, 3)
        assert np.allclose(p.normal, [0, 0, 1])
        iv = p.intervals(min_frames=10)
        assert len(iv) == 1  # one step per plate in this stair descent
        assert p.loaded.sum() > 80
        # every CoP inside its plate while loaded, on the surface plane, NaN when unloaded
        assert p.contains(p.cop[p.loaded]).all() and not p.cop_outside.any()
        assert np.allclose(p.height_above(p.cop[p.loaded]), 0.0, atol=1e-9)
        assert np.isnan(p.cop[~p.loaded]).all()
        fn = p.force[p.loaded] @ p.normal
        assert fn.min() > plates.threshold and fn.max() > 1000.0  # ground pushes up
        # free moment along the normal
        fm = p.free_moment[p.loaded]
        assert np.allclose(fm - np.outer(fm @ p.normal, p.normal), 0.0, atol=1e-9)
    # Nexus stores the ground reaction per kg, same sign (reaction on the subject, lab frame):
    # the box-averaged plate wrench equals it to the file's float precision.
    out = read_c3d_outputs(trial)
    for name, k in (("RGroundReactionForce", 3), ("LGroundReactionForce", 0)):
        g = out[name]
        ok = np.all(np.isfinite(g), axis=1)
        assert ok.sum() > 90
        err = np.abs(plates[k].force[ok] / MASS_KG - g[ok]).max()
        assert err < 1e-5, (name, err)


def test_analog_rate_matches_ezc3d(trial):
    ezc3d = pytest.importorskip("ezc3d")
    fa = read_force_plates(trial, at="analog")
    assert fa.rate == 1080.0 and fa.n_frames == 2907
    # raw noise (10-20 N) does not cut a stance: one loaded interval per plate, as at the point rate
    assert [len(p.intervals()) for p in fa] == [1, 1, 1, 1]
    c = ezc3d.c3d(str(trial), extract_forceplat_data=True)
    for k, p in enumerate(fa):
        e = c["data"]["platform"][k]
        assert np.allclose(p.force, e["force"].T, atol=1e-9)
        # ezc3d reports N.mm and mm: same moment at the plate origin, centre of pressure and free moment
        assert e["unit_moment"] == "Nmm" and e["unit_position"] == "mm"
        assert np.allclose(p.moment, e["moment"].T / 1000.0, atol=1e-6)
        L = p.loaded & np.all(np.isfinite(p.cop), axis=1)   # NaN: centre of pressure off the plate
        assert L.sum() > 0.95 * p.loaded.sum()
        assert np.allclose(p.cop[L], e["center_of_pressure"].T[L] / 1000.0, atol=1e-6)
        assert np.allclose(p.free_moment[L], e["Tz"].T[L] / 1000.0, atol=1e-6)
        lo = p.loaded & np.isfinite(p.cop[:, 0])  # loaded on the point-period average and at the sample
        assert lo.sum() > 0.98 * p.loaded.sum() > 700
        assert np.allclose(p.cop[lo] * 1e3, e["center_of_pressure"].T[lo], atol=1e-6)
        assert np.allclose(p.free_moment[lo] * 1e3, e["Tz"].T[lo], atol=1e-4)


def test_feet_assigned_from_markers(trial, plates):
    from kinematics.io.c3d import read_c3d

    contacts = assign_feet(plates, read_c3d(trial))
    assert [(c.plate, c.foot) for c in contacts] == [(3, "R"), (2, "L"), (1, "R"), (0, "L")]
    for c in contacts:
        other = "L" if c.foot == "R" else "R"
        assert c.cop_distance[c.foot] < 0.05 and c.cop_distance[other] > 0.15
        assert "two feet" not in c.flags and "cop outside plate" not in c.flags
    assert contacts[-1].flags == ("partial",) and not contacts[0].flags  # last stance runs to the trial's end
    assert all(c.usable for c in contacts)


def test_two_feet_on_one_plate_flagged(trial, plates):
    from kinematics.io.c3d import read_c3d
    from kinematics.io.markers import MarkerTrial

    mk = read_c3d(trial)
    c0 = assign_feet(plates, mk)[0]  # right foot on plate 4
    pos = mk.positions.copy()
    # put the left foot, standing still, next to the right one on plate 4 during that stance
    for name in ("LHEE", "LTOE", "LANK"):
        j = mk.index(name)
        r = pos[c0.start:c0.stop, mk.index("R" + name[1:])]
        pos[c0.start:c0.stop, j] = r.mean(axis=0) + np.array([0.0, 0.12, 0.0]) * np.sign(plates[3].centre[1] - r[:, 1].mean())
    moved = MarkerTrial(mk.names, pos, mk.rate, mk.time, mk.source)
    c = assign_feet(plates, moved)[0]
    assert c.plate == 3 and "two feet" in c.flags and c.foot is None and not c.usable


def test_cop_outside_plate_flagged(trial, modified):
    fp = read_force_plates(modified / "shrunk.c3d")
    p = fp[0]
    assert p.cop_outside.sum() > 10 and any("outside" in n for n in p.notes)
    from kinematics.io.c3d import read_c3d

    c = next(c for c in assign_feet(fp, read_c3d(trial)) if c.plate == 0)
    assert "cop outside plate" in c.flags and not c.usable


def test_analog_rate_not_consistent_refused(trial, tmp_path):
    # ANALOG:RATE 1000 Hz with 9 stored samples per 120 Hz frame (ezc3d will not write such a file,
    # so the parameter's float is patched in the parameter section)
    import struct

    data = trial.read_bytes()
    start = 512 * (data[0] - 1)
    key = b"RATE"
    i = data.index(key, start)
    while struct.unpack("<f", data[i + len(key) + 4:i + len(key) + 8])[0] != 1080.0:
        i = data.index(key, i + 1)
    j = i + len(key) + 4
    bad = tmp_path / "rate.c3d"
    bad.write_bytes(data[:j] + struct.pack("<f", 1000.0) + data[j + 4:])
    with pytest.raises(InputError, match="ANALOG:RATE 1000 Hz"):
        read_force_plates(bad)


def test_degenerate_corners_and_non_finite_channels_refused(modified):
    """Corrupt plate data is refused, never read as a plate that was never loaded (exit 0, kinematics only)."""
    with pytest.raises(InputError, match=r"nocorners\.c3d: force plate 1: FORCE_PLATFORM:CORNERS do not span"):
        read_force_plates(modified / "nocorners.c3d")
    with pytest.raises(InputError, match=r"nan_analog\.c3d: force plate 2: channel .* 1 non-finite sample\(s\) "
                                         r"\(first at analog sample 501\)"):
        read_force_plates(modified / "nan_analog.c3d")


def test_no_plates_kinematics_only(modified):
    fp = read_force_plates(modified / "noplates.c3d")
    assert len(fp) == 0 and "kinematics only" in fp.notes[0] and fp.n_frames == 323


def test_type4_calibration_matrix(trial, modified):
    fp4 = read_force_plates(modified / "type4.c3d", threshold=40.0)  # cal: gain 2, fx' = 2 fx + 0.5 fy
    ref = read_force_plates(trial, zero="none", at="points")
    p, q = fp4[0], ref[0]
    assert p.type == 4
    fp_plate, fq_plate = p.force @ p.rotation, q.force @ q.rotation  # back to the plate frame
    assert np.allclose(fp_plate[:, 2], 2 * fq_plate[:, 2], atol=1e-6)
    assert np.allclose(fp_plate[:, 0], 2 * fq_plate[:, 0] + 0.5 * fq_plate[:, 1], atol=1e-6)
    assert np.allclose(fp_plate[:, 1], 2 * fq_plate[:, 1], atol=1e-6)
    lo = p.loaded & q.loaded
    # CoP: the gain cancels; the cross-talk moves the moment transfer to the surface (sensor origin
    # 41 mm below it, o_z = -0.041 m along plate Z, which points down): dx = 0.25 f_y o_z / f_z
    cp, cq = (p.cop[lo] - p.centre) @ p.rotation, (q.cop[lo] - q.centre) @ q.rotation
    fy, fz = fq_plate[lo, 1], fq_plate[lo, 2]
    assert np.allclose(cp[:, 0], cq[:, 0] + 0.25 * fy * -0.041 / fz, atol=1e-9)
    assert np.allclose(cp[:, 1], cq[:, 1], atol=1e-9)


def test_missing_calibration_matrix_refused(modified):
    with pytest.raises(InputError, match="CAL_MATRIX"):
        read_force_plates(modified / "type4_nocal.c3d")


@pytest.mark.parametrize("fa", [1080.0, 1000.0, 600.0])
def test_box_average_is_centred_mean(fa):
    fp, n = 120.0, 60
    t = np.arange(int(n / fp * fa) + 20) / fa
    x = np.column_stack([3.0 + 2.0 * t, np.sin(2 * np.pi * 5 * t)])
    y = box_average(x, fa, fp, n)
    tk = np.arange(n) / fp
    inner = slice(1, n - 1)
    assert np.allclose(y[inner, 0], 3.0 + 2.0 * tk[inner], atol=1e-9)  # a ramp's mean is its centre value
    T = 1 / fp  # the box's transfer function for a sine: sinc(f T)
    assert np.allclose(y[inner, 1], np.sinc(5 * T) * np.sin(2 * np.pi * 5 * tk[inner]), atol=2e-3)


@pytest.mark.parametrize("name", ["type1.c3d", "type3.c3d"])
def test_types_1_and_3_give_the_type2_wrench(trial, modified, name):
    """Plate 1 rewritten as a type-1 (CoP channels) and a type-3 (Kistler 8-channel) platform."""
    ref = read_force_plates(trial, at="analog")[0]
    p = read_force_plates(modified / name, at="analog")[0]
    assert p.type == int(name[4])
    scale = np.abs(ref.force).max()
    assert np.abs(p.force - ref.force).max() < 1e-4 * scale
    both = np.isfinite(p.cop[:, 0]) & np.isfinite(ref.cop[:, 0]) & (ref.force @ ref.normal > 100.0)
    assert both.sum() > 600
    assert np.abs(p.cop[both] - ref.cop[both]).max() < 1e-5  # m (float32 channels)
    assert np.abs(p.free_moment[both] - ref.free_moment[both]).max() < 1e-3  # N m
