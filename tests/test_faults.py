"""Fault injection: every class of bad input and fault of issue S1, with real files.

Each case runs the command as a user would (``personalize.cli.main``) and asserts
the exit code, the one-line message (``error: <file>: <problem>``, no traceback)
and that nothing is left in ``--out``.  Classes: (1) the command line, (2)
file-system faults, (3) stale outputs, (4) inputs that would give silently wrong
results, (5) failures inside ``run``, (6) batch under worker faults (also
tests/test_cohort.py), (7) huge inputs, (8) progress output.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from kinematics.io.c3d import read_c3d, write_c3d
from kinematics.io.markers import MarkerTrial
from kinematics.io.storage import read_trc, write_trc
from personalize.cli import main

ROOT = os.geteuid() == 0 if hasattr(os, "geteuid") else False


def run_cli(capsys, *args) -> tuple[int, list[str]]:
    """Exit code and the stderr lines of ``personalize ARGS``."""
    capsys.readouterr()
    code = main([str(a) for a in args])
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error" not in err, err
    return code, [ln for ln in err.splitlines() if ln.strip()]


def one_error(lines: list[str], *needles: str) -> str:
    """The single ``error:`` line, containing every needle."""
    errs = [ln for ln in lines if ln.startswith("error: ")]
    assert len(errs) == 1, lines
    for n in needles:
        assert n in errs[0], (n, errs[0])
    return errs[0]


def empty_or_absent(p: Path) -> bool:
    return not p.exists() or (p.is_dir() and not any(p.iterdir()))


def no_staging(folder: Path) -> bool:
    return not [p for p in folder.iterdir() if ".staging-" in p.name or ".old-" in p.name or "probe" in p.name]


@pytest.fixture
def read_only(tmp_path):
    """A folder nobody can write into, root included (immutable attribute; permission bits for other users)."""
    d = tmp_path / "ro"
    d.mkdir()
    if ROOT:
        if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(d)]).returncode:
            pytest.skip("cannot make a folder read-only for root here")
        yield d
        subprocess.run(["chattr", "-i", str(d)])
    else:
        d.chmod(0o555)
        yield d
        d.chmod(0o755)


# --------------------------------------------------------------------------- inputs
@pytest.fixture(scope="module")
def subject(tmp_path_factory) -> Path:
    """A phantom SUBJECT_DIR (3 mm labels, short trials): real C3D, subject.json, truth.json."""
    from personalize.evaluation.phantom_subject import write_phantom_subject

    return write_phantom_subject(tmp_path_factory.mktemp("faults") / "subject", seed=1, voxel_mm=3.0)


@pytest.fixture
def subj_copy(subject, tmp_path) -> Path:
    d = tmp_path / "subject"
    shutil.copytree(subject, d)
    return d


def _markers_args(subject: Path, out: Path, trial: Path | None = None, static: Path | None = None, **kw):
    args = ["markers", trial or subject / "gait_01.c3d", "--method", "pig", "--subject", subject / "subject.json",
            "--out", out, "--no-plot"]
    if static is not None:
        args += ["--static", static]
    for k, v in kw.items():
        args += [f"--{k.replace('_', '-')}", v]
    return args


def _edit_labels(src: Path, dst: Path, edit) -> None:
    """Copy a C3D with its POINT:LABELS edited by `edit(labels) -> labels` (ezc3d writes it)."""
    import ezc3d

    c = ezc3d.c3d(str(src))
    labels = list(c["parameters"]["POINT"]["LABELS"]["value"])
    c["parameters"]["POINT"]["LABELS"]["value"] = edit(labels)
    c.write(str(dst))


# --------------------------------------------------------------------------- 1. the command line
def test_1_usage_errors(capsys, tmp_path):
    capsys.readouterr()
    assert main(["markers", "--bogus"]) == 2
    err = capsys.readouterr().err
    assert "No such option: --bogus" in err and "Usage: personalize markers" in err and "Traceback" not in err
    assert main([]) == 0 and "Usage: personalize" in capsys.readouterr().out


# --------------------------------------------------------------------------- 2. file-system faults
def test_2_read_only_out(capsys, subject, read_only, tmp_path):
    """A read-only --out: markers, surfaces, phantom, run, batch refuse before any work (exit 2)."""
    out = read_only / "result"
    cases = [
        _markers_args(subject, out),
        ["surfaces", subject / "labels.nii.gz", "--out", out, "--bones", "femur_r"],
        ["phantom", "--out", out, "--bones", "femur_r", "--no-motion"],
        ["run", subject, "--out", out, "--quiet"],
    ]
    (tmp_path / "m.csv").write_text(f"subject,path\ns1,{subject}\n")
    cases.append(["batch", tmp_path / "m.csv", "--out", out, "--workers", "1"])
    for args in cases:
        t0 = time.perf_counter()
        code, lines = run_cli(capsys, *args)
        assert code == 2, (args, lines)
        one_error(lines, str(out), "cannot write to", str(read_only))
        assert time.perf_counter() - t0 < 30          # refused before the work, not after it
        assert empty_or_absent(read_only)


def test_2_read_only_ik_out(capsys, shared_data, read_only):
    g = shared_data / "opensim_gait2392"
    code, lines = run_cli(capsys, "ik", g / "subject01_simbody.osim", g / "subject01_walk1.trc", "--out",
                          read_only / "walk.mot", "--quiet")
    assert code == 2
    one_error(lines, "walk.mot", "cannot write to")
    assert empty_or_absent(read_only)


def test_2_out_is_a_file(capsys, subject, tmp_path):
    f = tmp_path / "taken.txt"
    f.write_text("keep me")
    mot = tmp_path / "k.mot"
    shutil.copy(subject / "truth" / "gait_01.mot", mot)
    for args in (["run", subject, "--out", f, "--quiet"],
                 ["bones", subject / "labels.nii.gz", "--out", f, "--quiet"],
                 ["surfaces", subject / "labels.nii.gz", "--out", f],
                 ["correlate", mot, "--out", f, "--quiet"],
                 _markers_args(subject, f)):
        code, lines = run_cli(capsys, *args)
        assert code == 2, args
        one_error(lines, str(f), "is a file, not a folder")
        assert f.read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["k.mot", "taken.txt"]


def test_2_ik_out_is_a_folder_and_unreadable_inputs(capsys, subject, shared_data, tmp_path):
    g = shared_data / "opensim_gait2392"
    folder = tmp_path / "walk.mot"                    # a folder where the result file should go
    folder.mkdir()
    code, lines = run_cli(capsys, "ik", g / "subject01_simbody.osim", g / "subject01_walk1.trc", "--out", folder)
    assert code == 2
    one_error(lines, str(folder), "is an existing folder")
    assert empty_or_absent(folder)
    # an input that cannot be read: permission bits for a user, a folder where a file is expected for root
    bad = tmp_path / "walk.trc"
    if ROOT:
        bad.mkdir()
    else:
        shutil.copy(g / "subject01_walk1.trc", bad)
        bad.chmod(0)
    out = tmp_path / "o"
    for args in (["ik", g / "subject01_simbody.osim", bad, "--out", out / "x.mot"],
                 _markers_args(subject, out, trial=bad)):
        code, lines = run_cli(capsys, *args)
        assert code == 2
        one_error(lines, str(bad))
        assert empty_or_absent(out)


# --------------------------------------------------------------------------- 3. stale outputs
def test_3_existing_out_replaced_whole_or_refused(capsys, subject, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old_trial.mot").write_text("from an earlier run")
    code, lines = run_cli(capsys, *_markers_args(subject, out))
    assert code == 2
    one_error(lines, str(out), "already holds 1 file", "--overwrite")
    assert sorted(p.name for p in out.iterdir()) == ["old_trial.mot"]           # untouched
    code, _ = run_cli(capsys, *_markers_args(subject, out), "--overwrite")
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["angles.mot", "centres.trc", "report.json"]  # old file gone
    assert no_staging(tmp_path)
    # the input folder itself, or a folder inside it
    for o in (subject, subject / "results"):
        code, lines = run_cli(capsys, "run", subject, "--out", o, "--quiet", "--overwrite")
        assert code == 2
        one_error(lines, str(o), "input folder")
    assert not (subject / "results").exists() and not (subject / "report.html").exists()


# --------------------------------------------------------------------------- 4. silently wrong results
def test_4_duplicated_label_c3d(capsys, subject, tmp_path):
    """The second RKNE of a trial is not dropped: the file is refused (angles were 27-52 deg off)."""
    bad = tmp_path / "dup.c3d"
    _edit_labels(subject / "gait_01.c3d", bad, lambda labs: [("RKNE" if lab == "RTIB" else lab) for lab in labs])
    out = tmp_path / "out"
    code, lines = run_cli(capsys, *_markers_args(subject, out, trial=bad))
    assert code == 2
    one_error(lines, "dup.c3d", "marker label 'RKNE' is given twice")
    assert empty_or_absent(out)


def test_4_real_c3d_faults(capsys, shared_data, tmp_path):
    """mocap_pig's static trial: duplicated label, cut in half, header of 0 frames, two Vicon subjects."""
    import struct

    src = shared_data / "mocap_pig" / "Static_trial.c3d"
    data = src.read_bytes()
    files = {}
    files["dup"] = tmp_path / "dup.c3d"
    _edit_labels(src, files["dup"], lambda labs: [("RKNE" if lab == "RTIB" else lab) for lab in labs])
    files["cut"] = tmp_path / "cut.c3d"
    files["cut"].write_bytes(data[: len(data) // 2])
    zero = bytearray(data)
    struct.pack_into("<H", zero, 8, 0)                  # last frame 0 < first frame 1
    files["zero"] = tmp_path / "zero.c3d"
    files["zero"].write_bytes(bytes(zero))
    files["two"] = tmp_path / "two.c3d"
    _edit_labels(src, files["two"], lambda labs: [("Ann:" if i % 2 else "Bob:") + lab for i, lab in enumerate(labs)])
    expect = {"dup": "marker label 'RKNE' is given twice", "cut": "ends after 245 of the 498 frames",
              "zero": "the header says 0 frames", "two": "markers of 2 subjects (Ann, Bob): choose one"}
    vsk = shared_data / "mocap_pig" / "Test.vsk"
    for k, f in files.items():
        out = tmp_path / f"out_{k}"
        code, lines = run_cli(capsys, "markers", f, "--method", "pig", "--subject", vsk, "--out", out, "--no-plot")
        assert code == 2, (k, lines)
        one_error(lines, str(f), expect[k])
        assert empty_or_absent(out)
    # a subject chosen: its markers only, under their plain names
    tr = read_c3d(files["two"], subject="Bob")
    assert tr.extra["subject"] == "Bob" and "LFHD" in tr.names and "RFHD" not in tr.names
    assert tr.n_frames == 498


def test_4_absurd_trc_value(capsys, shared_data, tmp_path):
    g = shared_data / "opensim_gait2392"
    lines = (g / "subject01_walk1.trc").read_text().splitlines()
    row = lines[10].split("\t")
    row[5] = "1e300"
    lines[10] = "\t".join(row)
    bad = tmp_path / "walk.trc"
    bad.write_text("\n".join(lines) + "\n")
    out = tmp_path / "o"
    code, err = run_cli(capsys, "ik", g / "subject01_simbody.osim", bad, "--out", out / "walk.mot", "--quiet")
    assert code == 2
    one_error(err, "walk.trc: line 11: marker", "1e+297 m from the lab origin (bound 100 m)")
    assert empty_or_absent(out)


def test_4_synthetic_trc_and_c3d_values(tmp_path):
    """No shared data needed: an absurd TRC value, an infinite one, a C3D in metres holding millimetres."""
    from lowerlimb.errors import InputError

    rng = np.random.default_rng(0)
    tr = MarkerTrial(("A", "B", "C"), rng.uniform(-1, 1, (20, 3, 3)), 100.0, np.arange(20) / 100.0, "s")
    write_trc(tmp_path / "ok.trc", tr)
    np.testing.assert_allclose(read_trc(tmp_path / "ok.trc").positions, tr.positions, atol=1e-9)
    text = (tmp_path / "ok.trc").read_text().splitlines()
    for tok, msg in (("1e300", r"1e\+297 m"), ("inf", "inf m")):
        row = text[7].split("\t")
        row[3] = tok
        (tmp_path / "bad.trc").write_text("\n".join(text[:7] + ["\t".join(row)] + text[8:]) + "\n")
        with pytest.raises(InputError, match=msg):
            read_trc(tmp_path / "bad.trc")
    big = MarkerTrial(tr.names, tr.positions * 1000.0, 100.0, tr.time, "s")  # metres x 1000, written as mm
    write_c3d(tmp_path / "m.c3d", big)
    import ezc3d

    c = ezc3d.c3d(str(tmp_path / "m.c3d"))
    c["parameters"]["POINT"]["UNITS"]["value"] = ["m"]           # the unit slip: mm data declared as m
    c.write(str(tmp_path / "slip.c3d"))
    with pytest.raises(InputError, match="bound 100 m"):
        read_c3d(tmp_path / "slip.c3d")


def _scaled(src: Path, dst: Path, factor: float) -> None:
    """A trial of 'another person': every marker scaled about the pelvis centre."""
    tr = read_c3d(src)
    c = np.nanmean(np.stack([tr.marker(m) for m in ("RASI", "LASI", "RPSI", "LPSI")]), axis=(0, 1))
    write_c3d(dst, MarkerTrial(tr.names, c + factor * (tr.positions - c), tr.rate, tr.time, str(dst)))


def test_4_markers_of_another_person(capsys, subject, tmp_path):
    """markers combines a trial, a static and a subject file only when they are of one person (as run does)."""
    other = tmp_path / "other_static.c3d"
    _scaled(subject / "static.c3d", other, 1.15)
    out = tmp_path / "o"
    code, lines = run_cli(capsys, *_markers_args(subject, out, static=other))
    assert code == 2
    one_error(lines, "other_static.c3d", "does not match the measured")
    other_trial = tmp_path / "other_gait.c3d"
    _scaled(subject / "gait_01.c3d", other_trial, 1.15)
    code, lines = run_cli(capsys, *_markers_args(subject, out, trial=other_trial, static=subject / "static.c3d"))
    assert code == 2
    one_error(lines, "other_gait.c3d", "pelvis marker distances differ from the static trial")
    s = json.loads((subject / "subject.json").read_text())
    for k in s:
        if "leg_length" in k.lower() or "LegLength" in k:
            s[k] = s[k] * 1.2 if isinstance(s[k], (int, float)) else s[k]
    (tmp_path / "other.json").write_text(json.dumps(s))
    args = _markers_args(subject, out)
    args[args.index("--subject") + 1] = tmp_path / "other.json"
    code, lines = run_cli(capsys, *args)
    assert code == 2
    one_error(lines, "gait_01.c3d", "does not match the", "leg length")
    assert empty_or_absent(out)


@pytest.mark.slow
def test_4_run_with_bones_of_another_person(capsys, subject, tmp_path):
    """The MRI bones of a taller phantom with this subject's markers: refused by the pelvis registration gate."""
    from personalize.evaluation.phantom_subject import write_phantom_subject

    other = write_phantom_subject(tmp_path / "other", seed=3, voxel_mm=3.0)
    d = tmp_path / "mixed"
    shutil.copytree(subject, d)
    for f in ("labels.nii.gz", "label_map.json"):
        shutil.copy(other / f, d / f)
    out = tmp_path / "out"
    code, lines = run_cli(capsys, "run", d, "--out", out, "--quiet")
    assert code == 2
    one_error(lines, "labels.nii.gz", "pelvis registration", "chi-square gate", "not of the same person")
    assert sorted(p.name for p in out.iterdir()) == ["report.html"]
    assert "fails its chi-square gate" in (out / "report.html").read_text()


# --------------------------------------------------------------------------- 5. failures inside run
def _rewrite_static(path: Path, edit) -> None:
    tr = read_c3d(path)
    pos = tr.positions.copy()
    edit(tr, pos)
    write_c3d(path, MarkerTrial(tr.names, pos, tr.rate, tr.time, str(path)))


@pytest.mark.parametrize("fault", ["lasi_never_visible", "all_nan_static", "corrupt_truth", "truth_not_object"])
def test_5_run_failures_are_one_line_and_a_refusal_report(capsys, subj_copy, tmp_path, fault):
    static = subj_copy / "static.c3d"
    if fault == "lasi_never_visible":
        _rewrite_static(static, lambda tr, pos: pos.__setitem__((slice(None), tr.names.index("LASI")), np.nan))
        blame, msg = static, "marker(s) LASI never visible"
    elif fault == "all_nan_static":
        keep = 0

        def edit(tr, pos):
            pos[:] = np.nan
            pos[:, keep] = 0.1           # one marker left so that the file still has a trajectory
        _rewrite_static(static, edit)
        blame, msg = static, "no frame has both pelvis and foot markers"     # the lab cannot be read from it
    elif fault == "corrupt_truth":
        (subj_copy / "truth.json").write_text('{"joints": {"joints": ')
        blame, msg = subj_copy / "truth.json", "not readable JSON"
    else:
        (subj_copy / "truth.json").write_text("[1, 2]")
        blame, msg = subj_copy / "truth.json", "holds a JSON list, expected an object"
    out = tmp_path / "out"
    code, lines = run_cli(capsys, "run", subj_copy, "--out", out, "--quiet")
    assert code == 2
    line = one_error(lines, str(blame), msg)
    assert "differ by nan" not in line
    assert sorted(p.name for p in out.iterdir()) == ["report.html"]           # the refusal report only
    assert msg in (out / "report.html").read_text()
    assert no_staging(tmp_path)


def test_5_refusal_replaces_an_earlier_run_only_with_overwrite(capsys, subj_copy, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "model.osim").write_text("an earlier model")
    (subj_copy / "truth.json").write_text("not json")
    code, lines = run_cli(capsys, "run", subj_copy, "--out", out, "--quiet")
    assert code == 2
    one_error(lines, str(out), "--overwrite")
    assert (out / "model.osim").read_text() == "an earlier model"
    code, lines = run_cli(capsys, "run", subj_copy, "--out", out, "--quiet", "--overwrite")
    assert code == 2
    one_error(lines, "truth.json")
    assert sorted(p.name for p in out.iterdir()) == ["report.html"]           # no stale model beside the refusal


# --------------------------------------------------------------------------- 6. batch under worker faults
def test_6_batch_job_that_kills_its_worker(tmp_path, capsys):
    """One job segfaults its process: only its row says so, the other subject is complete; nothing staged."""
    for n in ("good", "crash"):
        (tmp_path / "data" / n).mkdir(parents=True)
    (tmp_path / "data" / "crash" / "fault.txt").write_text("segv")
    (tmp_path / "m.csv").write_text("subject,path\ngood,data/good\ncrash,data/crash\n")
    out = tmp_path / "out"
    code, lines = run_cli(capsys, "batch", tmp_path / "m.csv", "--out", out, "--workers", "1", "--retries", "0",
                          "--job", "cohort_jobs.segv_or_env_job")
    assert code == 1
    rows = {r.split(",")[0]: r for r in (out / "batch.csv").read_text().splitlines()[1:]}
    assert rows["good"].split(",")[1] == "ok"
    assert ",error,," in rows["crash"] and "killed by SIGSEGV" in rows["crash"] and "its only attempt" in rows["crash"]
    assert sorted(p.name for p in out.iterdir()) == ["batch.csv", "good"]
    assert any("batch [2/2]" in ln for ln in lines)            # plain progress lines: stderr is not a terminal


@pytest.mark.slow
def test_6_batch_sigterm_and_sigint(tmp_path):
    """SIGTERM / SIGINT stop the batch: exit 143 / 130, no traceback, batch.csv kept; a rerun resumes."""
    names = ["a", "b", "c", "d"]
    for n in names:
        (tmp_path / "data" / n).mkdir(parents=True)
    (tmp_path / "m.csv").write_text("subject,path\n" + "".join(f"{n},data/{n}\n" for n in names))
    out = tmp_path / "out"
    tests_dir = str(Path(__file__).resolve().parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([tests_dir, os.environ.get("PYTHONPATH", "")]),
           "COHORT_SLEEP": "2"}
    args = [sys.executable, "-m", "personalize", "batch", str(tmp_path / "m.csv"), "--out", str(out), "--workers", "1",
            "--job", "cohort_jobs.sleep_job"]
    for sig, code in ((signal.SIGTERM, 143), (signal.SIGINT, 130)):
        proc = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                start_new_session=True)
        done = len(list(out.glob("*/summary.json")))
        deadline = time.time() + 240
        while time.time() < deadline and len(list(out.glob("*/summary.json"))) == done:   # one more subject done
            time.sleep(0.2)
        time.sleep(0.5)
        os.killpg(proc.pid, sig) if sig == signal.SIGINT else proc.send_signal(sig)  # Ctrl-C reaches the group
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == code, err
        assert "Traceback" not in err, err
        assert f"interrupted ({signal.Signals(sig).name}): batch stopped" in err and "rerun" in err
        assert (out / "batch.csv").is_file()
        assert no_staging(out)
    proc = subprocess.run(args, env={**env, "COHORT_SLEEP": "0"}, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    rows = (out / "batch.csv").read_text().splitlines()[1:]
    assert [r.split(",")[:2] for r in rows][:2] == [["a", "skipped"], ["b", "skipped"]]   # resumed
    assert all(r.split(",")[1] in ("ok", "skipped") for r in rows) and len(rows) == 4


# --------------------------------------------------------------------------- 7. huge inputs
def test_7_huge_xml_refused_before_parsing(capsys, tmp_path, shared_data):
    g = shared_data / "opensim_gait2392"
    huge = tmp_path / "huge.osim"
    with open(huge, "w") as f:
        f.write('<?xml version="1.0"?>\n<OpenSimDocument Version="40000"><Model name="m"><!--')
        f.write("x" * (51 * 2**20))
        f.write("--></Model></OpenSimDocument>\n")
    out = tmp_path / "o"
    t0 = time.perf_counter()
    code, lines = run_cli(capsys, "ik", huge, g / "subject01_walk1.trc", "--out", out / "w.mot", "--quiet")
    assert code == 2
    one_error(lines, "huge.osim", "XML file of 51 MB is over the 50 MB bound", "refused before parsing")
    assert empty_or_absent(out)
    assert time.perf_counter() - t0 < 60


def test_7_long_xml_token_is_read(tmp_path):
    """A 5 MB attribute (one token longer than any parser chunk) is read, linearly, from one buffer."""
    from kinematics.io.opensim_io import check_osim_file, read_xml

    p = tmp_path / "long.osim"
    p.write_text('<?xml version="1.0"?><OpenSimDocument Version="40000"><Model name="' + "m" * 5_000_000
                 + '"></Model></OpenSimDocument>')
    check_osim_file(p)
    assert len(read_xml(p, "x", "y").find("Model").get("name")) == 5_000_000


# --------------------------------------------------------------------------- 8. progress
def test_8_plain_progress_lines_when_not_a_terminal():
    import io

    from rich.console import Console

    from personalize.progress import StepProgress

    buf = io.StringIO()
    with StepProgress("run", 4, Console(file=buf, force_terminal=False, width=200)) as prog:
        for m in ("reading inputs", "detecting landmarks", "IK gait_01"):
            prog(m)
    lines = buf.getvalue().splitlines()
    assert lines[0].startswith("run [1/~4]") and lines[0].endswith("reading inputs") and "elapsed" in lines[0]
    assert "left" in lines[2] and lines[2].endswith("IK gait_01")
    assert lines[-1].startswith("run: 3 steps in ")


def test_3_phantom_out_equal_to_its_anatomy_folder_is_refused_and_the_bones_kept(capsys, tmp_path):
    # with --overwrite, an --out equal to the input folder would be set aside and deleted
    anatomy = tmp_path / "bones"
    anatomy.mkdir()
    (anatomy / "femur_r.ply").write_bytes(b"ply\n")
    code, lines = run_cli(capsys, "phantom", "--anatomy", str(anatomy), "--out", str(anatomy), "--overwrite")
    assert code == 2
    one_error(lines, str(anatomy))
    assert (anatomy / "femur_r.ply").read_bytes() == b"ply\n"
