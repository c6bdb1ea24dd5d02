"""Property-based fault injection into the file readers (hypothesis).

Valid C3D, TRC, MOT and PLY files are corrupted at random (bytes flipped,
inserted, deleted, chunks repeated, the file cut short; for the text formats
also one value replaced by a hostile token).  Every read must end in a correct
result or in one `InputError` whose message is one line naming the file; any
other exception is a failure (a traceback a user would see).  "Correct":

* a replaced value is read back as that value (in SI), or the file is refused;
* whatever is read satisfies what the reader promises: unique names, shapes
  that agree, finite or NaN samples within the stated bounds, increasing time,
  as many frames as the file states.

Each reader gets at least 500 cases (``FUZZ_CASES``), derandomised (the same
cases every run).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lowerlimb.errors import InputError
from kinematics.io.markers import MarkerTrial

FUZZ_CASES = 500
SETTINGS = settings(max_examples=FUZZ_CASES, deadline=None, derandomize=True, database=None,
                    suppress_health_check=list(HealthCheck))

# --------------------------------------------------------------------------- corruptions
_TOKENS = ["", "nan", "NaN", "inf", "-inf", "1e300", "-1e300", "1e-320", "abc", "0x10", "--1", "1e", "١٢",
           "9" * 400, "0", "-0", "1,5", "\t", " ", "1e7", "123456789.0"]

byte_edit = st.tuples(st.sampled_from(["flip", "insert", "delete", "repeat", "truncate", "zero"]),
                      st.floats(0.0, 1.0, exclude_max=True), st.integers(1, 64), st.binary(min_size=1, max_size=16))


def corrupt_bytes(data: bytes, edits) -> bytes:
    b = bytearray(data)
    for kind, where, n, payload in edits:
        if not b:
            break
        i = int(where * len(b))
        if kind == "flip":
            b[i] ^= (payload[0] or 1)
        elif kind == "insert":
            b[i:i] = payload
        elif kind == "delete":
            del b[i:i + n]
        elif kind == "repeat":
            b[i:i] = b[i:i + n]
        elif kind == "truncate":
            del b[i:]
        else:
            b[i:i + n] = bytes(min(n, len(b) - i))
    return bytes(b)


def _one_line_error(exc: InputError, path: Path) -> None:
    msg = str(exc)
    assert "\n" not in msg and "\r" not in msg, msg
    assert msg.startswith(str(path)), msg
    assert len(msg) < 1000, msg


class Cases:
    """Counts the cases a hypothesis test ran (>= FUZZ_CASES asserted by the caller)."""

    def __init__(self):
        self.n = self.refused = 0


def read_or_refuse(read, path: Path, cases: Cases):
    """read(path), or None when it refuses the file with a one-line `InputError` naming it (counted)."""
    try:
        return read(path)
    except InputError as exc:
        _one_line_error(exc, path)
        cases.refused += 1
        return None


# --------------------------------------------------------------------------- seeds
def _trial(n_frames=12, names=("RASI", "LASI", "RKNE", "LKNE", "RANK")) -> MarkerTrial:
    rng = np.random.default_rng(0)
    pos = rng.uniform(-1.0, 1.5, (n_frames, len(names), 3))
    pos[3, 1] = np.nan                                   # one gap
    return MarkerTrial(tuple(names), pos, 100.0, np.arange(n_frames) / 100.0, "seed")


@pytest.fixture(scope="module")
def seeds(tmp_path_factory, request) -> dict[str, Path]:
    import trimesh

    from kinematics.io.c3d import write_c3d
    from kinematics.io.storage import write_mot, write_trc

    d = tmp_path_factory.mktemp("seeds")
    tr = _trial()
    write_c3d(d / "s.c3d", tr)
    write_trc(d / "s.trc", tr)
    t = np.arange(15) / 50.0
    write_mot(d / "s.mot", ["hip_flexion_r", "knee_angle_r", "pelvis_tx"], t,
              np.stack([np.sin(t), np.cos(t), 0.1 * t], axis=1), rotational=["hip_flexion_r", "knee_angle_r"])
    m = trimesh.creation.icosphere(subdivisions=1, radius=20.0)
    (d / "s.ply").write_bytes(trimesh.exchange.ply.export_ply(m, encoding="binary"))
    (d / "a.ply").write_bytes(trimesh.exchange.ply.export_ply(m, encoding="ascii"))
    return {"c3d": d / "s.c3d", "trc": d / "s.trc", "mot": d / "s.mot", "ply": d / "s.ply", "ply_ascii": d / "a.ply"}


# --------------------------------------------------------------------------- checks of a result
def check_trial(tr: MarkerTrial, bound: float) -> None:
    F, M = tr.positions.shape[:2]
    assert tr.positions.shape == (F, M, 3) and len(tr.names) == M and len(set(tr.names)) == M
    assert tr.time.shape == (F,) and F >= 1 and np.all(np.isfinite(tr.time))
    p = tr.positions[np.isfinite(tr.positions)]
    assert np.all(np.abs(p) <= bound)
    # a sample is whole or missing
    assert np.array_equal(np.isnan(tr.positions).any(axis=2), np.isnan(tr.positions).all(axis=2))
    assert math.isfinite(tr.rate) and tr.rate > 0


def _read_c3d_case(path: Path, cases: Cases):
    from kinematics.io.c3d import _header_frames, read_c3d
    from kinematics.io.markers import MAX_COORDINATE_M

    tr = read_or_refuse(read_c3d, path, cases)
    if tr is None:
        return
    check_trial(tr, MAX_COORDINATE_M)
    assert np.all(np.diff(tr.time) > 0)
    n = _header_frames(path)
    assert n is None or tr.n_frames == n          # never fewer frames than the file states


@pytest.mark.slow
def test_fuzz_c3d(seeds, tmp_path):
    data = seeds["c3d"].read_bytes()
    cases = Cases()
    path = tmp_path / "f.c3d"

    @SETTINGS
    @given(st.lists(byte_edit, min_size=1, max_size=4))
    def case(edits):
        path.write_bytes(corrupt_bytes(data, edits))
        _read_c3d_case(path, cases)
        cases.n += 1

    case()
    assert cases.n >= FUZZ_CASES
    assert 0 < cases.refused < cases.n               # both outcomes happen


def _text_edit():
    return st.one_of(
        st.tuples(st.just("token"), st.integers(0, 10**6), st.integers(0, 10**6), st.sampled_from(_TOKENS)),
        st.tuples(st.just("line"), st.sampled_from(["drop", "repeat", "blank"]), st.integers(0, 10**6), st.just("")),
        st.tuples(st.just("bytes"), st.lists(byte_edit, min_size=1, max_size=3), st.just(0), st.just("")))


def _apply_text(text: str, edit, data_start: int):
    """The corrupted text and, for a replaced data value, (row, field, token)."""
    kind, a, b, tok = edit
    lines = text.split("\n")
    if kind == "token":
        rows = [i for i in range(data_start, len(lines)) if lines[i].strip()]
        if not rows:
            return text, None
        i = rows[a % len(rows)]
        sep = "\t"
        fields = lines[i].split(sep)
        if len(fields) < 2:
            return text, None
        j = 1 + b % (len(fields) - 1)   # not the frame number / keep the time column reachable
        fields[j] = tok
        lines[i] = sep.join(fields)
        return "\n".join(lines), (rows.index(i), j, tok)
    if kind == "line":
        i = b % len(lines)
        if a == "drop":
            del lines[i]
        elif a == "repeat":
            lines.insert(i, lines[i])
        else:
            lines.insert(i, "")
        return "\n".join(lines), None
    return corrupt_bytes(_enc(text), a).decode("utf-8", "surrogateescape"), None


def _enc(text: str) -> bytes:
    return text.encode("utf-8", "surrogateescape")


def _expected(tok: str) -> float | None:
    try:
        return float(tok) if tok.strip() else math.nan
    except ValueError:
        return None


def _check_trc(tr, ref, replaced) -> None:
    from kinematics.io.markers import MAX_COORDINATE_M

    check_trial(tr, MAX_COORDINATE_M)
    assert np.all(np.diff(tr.time) > 0)
    if replaced is None:
        return
    row, field, tok = replaced
    want = _expected(tok)
    assert want is not None                   # a non-number was accepted
    if field == 1:
        assert tr.time[row] == want
    elif field >= 2 + 3 * len(ref.names):
        assert not tok.strip()                # a value beyond the markers' columns is refused
    else:
        m, c = divmod(field - 2, 3)
        got = tr.positions[row, m]
        if math.isnan(want):
            assert np.isnan(got).all()        # a gap is the whole sample
        else:
            assert got[c] == pytest.approx(want * 1e-3, rel=1e-12, abs=0)
            keep = [k for k in range(3) if k != c]
            assert np.allclose(got[keep], ref.positions[row, m, keep], equal_nan=True)


def _check_mot(tab, ref, replaced) -> None:
    from kinematics.io.storage import MAX_TABLE_VALUE

    assert tab.values.shape == (tab.time.shape[0], len(tab.columns)) and len(set(tab.columns)) == len(tab.columns)
    assert np.all(np.isfinite(tab.time)) and np.all(np.diff(tab.time) >= 0)
    v = tab.values[~np.isnan(tab.values)]
    assert np.all(np.abs(v) <= MAX_TABLE_VALUE)
    if replaced is None:
        return
    row, field, tok = replaced
    want = _expected(tok)
    assert want is not None and tok.strip()   # neither a non-number nor a missing field is accepted
    got = tab.values[row, field - 1]            # MOT fields: time, then the columns
    if math.isnan(want):
        assert math.isnan(got)
    else:
        assert got == want
        other = [k for k in range(len(tab.columns)) if k != field - 1]
        assert np.array_equal(tab.values[row, other], ref.values[row, other])


# reader, first data line of the seed (TRC: after its 5 header lines and a blank one; MOT: after "time..."), check
TEXT_FORMATS = {
    "trc": ("read_trc", lambda lines: 6, _check_trc),
    "mot": ("read_mot", lambda lines: next(i for i, ln in enumerate(lines) if ln.startswith("time")) + 1, _check_mot),
}


@pytest.mark.parametrize("fmt", [pytest.param("trc", marks=pytest.mark.slow), "mot"])
def test_fuzz_text(seeds, tmp_path, fmt):
    from kinematics.io import storage

    reader, first_data_line, check = TEXT_FORMATS[fmt]
    read = getattr(storage, reader)
    text = seeds[fmt].read_text()
    data_start = first_data_line(text.split("\n"))
    ref = read(seeds[fmt])
    cases = Cases()
    path = tmp_path / f"f.{fmt}"

    @SETTINGS
    @given(st.lists(_text_edit(), min_size=1, max_size=3))
    def case(edits):
        t, replaced = text, None
        for e in edits:
            t, r = _apply_text(t, e, data_start)
            replaced = r if len(edits) == 1 else None
        path.write_bytes(_enc(t))
        cases.n += 1
        result = read_or_refuse(read, path, cases)
        if result is not None:
            check(result, ref, replaced)

    case()
    assert cases.n >= FUZZ_CASES and 0 < cases.refused < cases.n


@pytest.mark.parametrize("seed_name", ["ply", "ply_ascii"])
def test_fuzz_ply(seeds, tmp_path, seed_name):
    from personalize.io.meshes import _load_mesh_file

    data = seeds[seed_name].read_bytes()
    cases = Cases()
    path = tmp_path / "f.ply"
    n_cases = FUZZ_CASES if seed_name == "ply" else FUZZ_CASES // 5

    @settings(SETTINGS, max_examples=n_cases)
    @given(st.lists(byte_edit, min_size=1, max_size=4))
    def case(edits):
        path.write_bytes(corrupt_bytes(data, edits))
        cases.n += 1
        loaded = read_or_refuse(_load_mesh_file, path, cases)
        if loaded is None:
            return
        mesh = loaded[0]
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        assert v.ndim == 2 and v.shape[1] == 3 and np.all(np.isfinite(v))
        assert f.ndim == 2 and f.shape[1] == 3 and len(f) and f.min() >= 0 and f.max() < len(v)

    case()
    assert cases.n >= n_cases and 0 < cases.refused < cases.n


def test_fuzz_real_seeds(shared_data, tmp_path):
    """The same corruptions of real files: a Vicon C3D (10 frames of mocap_pig's static) and OpenSim's walk TRC."""
    from kinematics.io.c3d import read_c3d, write_c3d
    from kinematics.io.markers import MAX_COORDINATE_M
    from kinematics.io.storage import read_trc

    st_trial = read_c3d(shared_data / "mocap_pig" / "Static_trial.c3d")
    small = MarkerTrial(st_trial.names[:20], st_trial.positions[:10, :20], st_trial.rate, st_trial.time[:10], "s")
    seed = tmp_path / "real.c3d"
    write_c3d(seed, small)
    data = seed.read_bytes()
    trc = (shared_data / "opensim_gait2392" / "subject01_walk1.trc").read_text()
    trc = "\n".join(trc.split("\n")[:40])             # header + first frames: its NumFrames then disagrees ...
    cases = Cases()
    path_c, path_t = tmp_path / "f.c3d", tmp_path / "f.trc"

    @settings(SETTINGS, max_examples=100)
    @given(st.lists(byte_edit, min_size=1, max_size=3), st.lists(byte_edit, min_size=1, max_size=3))
    def case(edits_c, edits_t):
        path_c.write_bytes(corrupt_bytes(data, edits_c))
        _read_c3d_case(path_c, cases)
        path_t.write_bytes(corrupt_bytes(trc.encode(), edits_t))
        try:
            check_trial(read_trc(path_t), MAX_COORDINATE_M)
        except InputError as exc:
            _one_line_error(exc, path_t)
        cases.n += 1

    case()
    assert cases.n >= 100
    with pytest.raises(InputError, match="frames"):       # ... which the reader notices
        path_t.write_text(trc)
        read_trc(path_t)
