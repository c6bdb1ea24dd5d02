"""The CLI shell: exit codes and one-line errors."""
from __future__ import annotations

import subprocess
import sys

import typer

from personalize import cli


def test_exit_codes_are_propagated(monkeypatch):
    app = typer.Typer()

    @app.command()
    def fail(code: int = 3) -> None:
        raise typer.Exit(code)

    @app.command()
    def ok() -> None:
        pass

    monkeypatch.setattr(cli, "app", app)
    assert cli.main(["fail", "--code", "3"]) == 3
    assert cli.main(["ok"]) == 0


def test_bad_input_is_one_line_and_exit_2(tmp_path):
    missing = tmp_path / "nothing.nii.gz"
    proc = subprocess.run([sys.executable, "-m", "personalize", "surfaces", str(missing), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "nothing.nii.gz" in lines[0]
    assert "Traceback" not in proc.stderr and not (tmp_path / "o").exists()


def _run(*args):
    return subprocess.run([sys.executable, "-m", "personalize", *args], capture_output=True, text=True)


def test_usage_errors_print_usage_and_exit_2():
    for args, msg in ((["--bogus"], "No such option: --bogus"), (["run"], "Missing argument 'subject_dir'"),
                      (["ik", "a.osim", "b.trc"], "Missing option '--out'"),
                      (["markers", "t.c3d", "--out"], "Option '--out' requires an argument")):
        proc = _run(*args)
        assert proc.returncode == 2, args
        assert msg in proc.stderr and "Usage: personalize" in proc.stderr or msg in proc.stderr, proc.stderr
        assert "internal error" not in proc.stderr and "Traceback" not in proc.stderr


def test_bare_command_prints_help_and_version():
    import personalize

    proc = _run()
    assert proc.returncode == 0 and "Usage: personalize" in proc.stdout and "batch" in proc.stdout
    assert proc.stderr == ""
    proc = _run("--version")
    assert proc.returncode == 0 and proc.stdout.strip() == f"personalize {personalize.__version__}"
    assert personalize.__version__.count(".") >= 1
    assert cli.main(["--version"]) == 0


def test_run_full_meshes_option_reaches_the_pipeline(monkeypatch, tmp_path):
    """``personalize run --full-meshes`` writes the meshes whole; by default they are decimated."""
    import personalize.pipeline

    seen = []

    def fake_run_subject(subject_dir, out, **kw):
        seen.append(kw["full_meshes"])
        return {"subject": "s", "ik": {}}

    monkeypatch.setattr(personalize.pipeline, "run_subject", fake_run_subject)
    assert cli.main(["run", str(tmp_path), "--out", str(tmp_path / "o"), "--full-meshes", "-q"]) == 0
    assert cli.main(["run", str(tmp_path), "--out", str(tmp_path / "o"), "-q"]) == 0
    assert seen == [True, False]
