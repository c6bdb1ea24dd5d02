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
