"""personalize.cohort and ``personalize batch``: manifest checks, error rows, resumption, retries."""
from __future__ import annotations

import csv
import json
import os
import shutil
from pathlib import Path

import pytest

from lowerlimb.errors import InputError
from personalize.cli import main
from personalize.cohort import Subject, read_batch_csv, read_manifest, run_batch
from personalize.cohort.records import is_complete

JOBS = "cohort_jobs"  # tests/cohort_jobs.py, importable by the workers (pytest puts tests/ on sys.path)


@pytest.fixture(scope="module")
def phantom_subject(tmp_path_factory) -> Path:
    """One small phantom subject folder (femur_r only, 3 mm voxels) copied for every cohort test."""
    from lowerlimb.atomic import staged_dir
    from phantoms import make_phantom
    from phantoms.imaging import write_phantom

    d = tmp_path_factory.mktemp("phantom") / "s"
    with staged_dir(d) as stage:
        write_phantom(stage, make_phantom(seed=3), voxel=(3e-3,) * 3, seed=3, bones=["femur_r"])
    return d


@pytest.fixture(scope="module")
def cluster():
    """One 2-worker LocalCluster shared by the module's tests (start-up costs seconds)."""
    from personalize.cohort.runner import dask_client

    with dask_client(None, workers=2) as client:
        yield client


def _cohort(root: Path, src: Path, names) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for n in names:
        shutil.copytree(src, root / "data" / n)
    (root / "manifest.csv").write_text("subject,path\n" + "".join(f"{n},data/{n}\n" for n in names))
    return root / "manifest.csv"


def _exit_code(args) -> int:
    """Exit code of the installed command (click's standalone mode, as ``personalize ...`` runs it)."""
    from typer.testing import CliRunner

    from personalize.cli import app

    return CliRunner().invoke(app, args).exit_code


def _csv_rows(path: Path) -> dict[str, dict]:
    with open(path, newline="") as f:
        return {r["subject"]: r for r in csv.DictReader(f)}


def test_manifest_is_validated(tmp_path):
    (tmp_path / "a").mkdir()
    m = tmp_path / "m.csv"
    cases = {
        "name,folder\na,a\n": "missing column(s) subject, path",
        "subject,path\n../evil,a\n": "row 2: subject id '../evil' is not a safe folder name",
        "subject,path\na/b,a\n": "not a safe folder name",
        "subject,path\nA,a\na,a\n": "row 3: subject id 'a' repeats row 2",
        "subject,path\nb,missing\n": "row 2 (b): subject folder",
        "subject,path\n": "lists no subjects",
    }
    for text, msg in cases.items():
        m.write_text(text)
        with pytest.raises(InputError, match=msg.replace("(", r"\(").replace(")", r"\)")) as e:
            read_manifest(m)
        assert e.value.source == str(m)
    m.write_text("Subject , Path,notes\ns1, a ,x\n")      # case/space-insensitive header, extra column ignored
    assert read_manifest(m) == [Subject("s1", (tmp_path / "a").resolve())]
    assert main(["batch", str(tmp_path / "none.csv"), "--out", str(tmp_path / "o")]) == 2


def test_batch_error_row_and_resumption(tmp_path, phantom_subject):
    """Done-when: 4 phantom subjects on 2 workers, one with corrupt labels: 3 results + 1 error row; rerun skips 3."""
    manifest = _cohort(tmp_path, phantom_subject, ["s1", "s2", "bad", "s4"])
    labels = tmp_path / "data" / "bad" / "labels.nii.gz"
    labels.write_bytes(labels.read_bytes()[:200])  # truncated gzip
    out = tmp_path / "out"
    args = ["batch", str(manifest), "--out", str(out), "--workers", "2", "--job", f"{JOBS}.label_volume_job"]
    assert _exit_code(args) == 1                               # some subject failed
    rows = _csv_rows(out / "batch.csv")
    assert list(rows) == ["s1", "s2", "bad", "s4"]             # manifest order
    assert {s: r["status"] for s, r in rows.items()} == {"s1": "ok", "s2": "ok", "bad": "error", "s4": "ok"}
    assert "labels.nii.gz" in rows["bad"]["error"] and "cannot read NIfTI" in rows["bad"]["error"]
    assert rows["bad"]["error"].startswith("input error: ")
    assert not (out / "bad").exists()                          # nothing published for the failed subject
    for s in ("s1", "s2", "s4"):
        assert is_complete(out / s)
        summary = json.loads((out / s / "summary.json").read_text())
        assert json.loads((out / s / "volumes.json").read_text())["bones"] == summary["volumes_ml"]
        v = summary["volumes_ml"]["femur_r"]
        # voxel-count volume of the label map against the exact phantom surface (3 mm voxels)
        assert v["labels_ml"] == pytest.approx(v["mesh_ml"], rel=0.05)
        assert 150 < v["mesh_ml"] < 800
        # one BLAS/OpenMP thread per worker; dask's MALLOC_TRIM_THRESHOLD_=65536 not imposed (user's value kept)
        assert summary["env"]["OMP_NUM_THREADS"] == summary["env"]["OPENBLAS_NUM_THREADS"] == "1"
        assert summary["env"]["MALLOC_TRIM_THRESHOLD_"] == os.environ.get("MALLOC_TRIM_THRESHOLD_")
        assert float(rows[s]["seconds"]) > 0
    assert not list(out.glob(".*staging*"))                    # no staging leftovers
    before = {s: (out / s / "summary.json").stat().st_mtime_ns for s in ("s1", "s2", "s4")}

    # second run: the three finished subjects are skipped, the bad one is tried again
    assert _exit_code(args) == 1
    rows = _csv_rows(out / "batch.csv")
    assert {s: r["status"] for s, r in rows.items()} == {"s1": "skipped", "s2": "skipped", "bad": "error", "s4": "skipped"}
    assert {s: (out / s / "summary.json").stat().st_mtime_ns for s in before} == before


def test_worker_death_is_retried(tmp_path, phantom_subject, cluster):
    """A job that kills its worker process on the first attempt still completes."""
    subjects = []
    for n in ("c1", "c2"):
        (tmp_path / n).mkdir()
        subjects.append(Subject(n, tmp_path / n))
    res = run_batch(subjects, tmp_path / "out", job=f"{JOBS}:crash_once_job", scheduler=cluster, progress=False)
    assert res.counts == {"ok": 2, "error": 0, "skipped": 0}
    for n in ("c1", "c2"):
        s = json.loads((tmp_path / "out" / n / "summary.json").read_text())
        assert s["crashed_pid"] != s["worker_pid"]             # the retry ran in another process
    assert [r.status for r in read_batch_csv(res.csv)] == ["ok", "ok"]


def test_unexpected_errors_are_retried_then_reported(tmp_path, cluster):
    import cohort_jobs

    for n in ("flaky", "bug"):
        (tmp_path / n).mkdir()
    out = tmp_path / "out"
    res = run_batch([Subject("flaky", tmp_path / "flaky")], out, job=cohort_jobs.flaky_job, scheduler=cluster,
                    progress=False)
    assert res.by_subject()["flaky"].status == "ok"
    res = run_batch([Subject("bug", tmp_path / "bug")], out, job=cohort_jobs.bug_job, scheduler=cluster,
                    retries=1, progress=False)
    r = res.by_subject()["bug"]
    assert r.status == "error" and "internal error (RuntimeError: a bug in the job)" in r.error
    assert (tmp_path / "bug" / "bug.count").read_text() == "2"  # 1 + retries attempts
    assert not (out / "bug").exists()
    # the first run's row is not in this run's table; resumption keeps "flaky" complete
    assert is_complete(out / "flaky")


def test_batch_command_refuses_unknown_job(tmp_path, capsys):
    (tmp_path / "a").mkdir()
    (tmp_path / "m.csv").write_text("subject,path\ns1,a\n")
    assert main(["batch", str(tmp_path / "m.csv"), "--out", str(tmp_path / "o"), "--job", "cohort_jobs.nope"]) == 2
    assert "cohort_jobs has no function nope" in capsys.readouterr().err
    assert main(["batch", str(tmp_path / "m.csv"), "--out", str(tmp_path / "o"), "--workers", "0",
                 "--job", "cohort_jobs.flaky_job"]) == 2
    assert "--workers: 0 is outside 1-256" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()              # refused before anything is written


@pytest.mark.slow
def test_batch_survives_dying_jobs_three_times(tmp_path, phantom_subject):
    """Done-when: 6 subjects, one job exits its process, one segfaults, one has a corrupt input; 3 runs into one --out."""
    names = ["s1", "s2", "exit", "s4", "segv", "bad"]
    manifest = _cohort(tmp_path, phantom_subject, names)
    (tmp_path / "data" / "exit" / "fault.txt").write_text("exit")
    (tmp_path / "data" / "segv" / "fault.txt").write_text("segv")
    labels = tmp_path / "data" / "bad" / "labels.nii.gz"
    labels.write_bytes(labels.read_bytes()[:200])
    out = tmp_path / "out"
    base = ["batch", str(manifest), "--out", str(out), "--workers", "2", "--retries", "1", "--job", f"{JOBS}.fault_job"]
    expected = {"s1": "ok", "s2": "ok", "exit": "error", "s4": "ok", "segv": "error", "bad": "error"}
    first = None
    for run, extra in enumerate(([], [], ["--rerun"])):
        assert _exit_code(base + extra) == 1                    # documented: 1 when some subject failed
        rows = _csv_rows(out / "batch.csv")
        assert list(rows) == names
        status = {s: r["status"] for s, r in rows.items()}
        if run == 1:                                           # resumed: the complete subjects are skipped
            assert status == {s: ("skipped" if v == "ok" else v) for s, v in expected.items()}
        else:
            assert status == expected
        assert rows["exit"]["error"] == ("the job's process exited with code 3 without a result, "
                                         "on each of 2 attempts")
        assert rows["segv"]["error"].startswith("the job's process killed by SIGSEGV (a crash in native code)")
        assert rows["bad"]["error"].startswith("input error: ") and "labels.nii.gz" in rows["bad"]["error"]
        errors = {s: rows[s]["error"] for s in ("exit", "segv", "bad")}
        assert first is None or errors == first               # the same rows every time
        first = errors
        for s in ("s1", "s2", "s4"):
            assert is_complete(out / s) and sorted(p.name for p in (out / s).iterdir()) == ["summary.json", "volumes.json"]
            v = json.loads((out / s / "volumes.json").read_text())["bones"]["femur_r"]
            assert v["labels_ml"] == pytest.approx(v["mesh_ml"], rel=0.05)
        for s in ("exit", "segv", "bad"):
            assert not (out / s).exists()                      # nothing published for a failed subject
        assert sorted(p.name for p in out.iterdir()) == sorted(["batch.csv", "s1", "s2", "s4"])  # no staging left
