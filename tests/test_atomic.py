"""Atomic outputs: complete files or none, paths kept inside the output folder."""
from __future__ import annotations

import os
import stat

import pytest

from lowerlimb.atomic import atomic_path, inside, staged_dir, write_text
from lowerlimb.errors import InputError


def test_atomic_path_publishes_only_on_success(tmp_path):
    target = tmp_path / "a.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert not target.exists() and list(tmp_path.iterdir()) == []
    write_text(target, "whole")
    assert target.read_text() == "whole"


def test_written_files_follow_the_umask(tmp_path):
    umask = os.umask(0)
    os.umask(umask)
    path = write_text(tmp_path / "b.json", "{}")
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask


def test_staged_dir_leaves_out_untouched_on_error(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(ValueError):
        with staged_dir(out) as stage:
            (stage / "x.txt").write_text("x")
            raise ValueError("bad input")
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == []
    with staged_dir(out) as stage:
        (stage / "sub").mkdir()
        (stage / "sub" / "y.txt").write_text("y")
    assert (out / "sub" / "y.txt").read_text() == "y"


def test_inside_refuses_escaping_paths(tmp_path):
    assert inside(tmp_path, "a/b.txt") == (tmp_path / "a" / "b.txt").resolve()
    for bad in ("../x.txt", "/etc/passwd", "a/../../x"):
        with pytest.raises(InputError):
            inside(tmp_path, bad)
