"""Atomic outputs: nothing half-written ever appears under an output path.

Files are written to a temporary name in the destination folder and renamed
(`os.replace`) once complete; whole result folders are staged in a temporary
sibling folder and moved in file by file only when the job succeeded.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from lowerlimb.errors import InputError

# mkstemp creates private (0600) files; outputs get the usual permissions of the user's umask.
_UMASK = os.umask(0)
os.umask(_UMASK)
_FILE_MODE = 0o666 & ~_UMASK


def inside(root: str | os.PathLike, relative: str | os.PathLike) -> Path:
    """Return ``root/relative``, refusing any path that escapes `root`.

    Raises
    ------
    InputError
        If `relative` is absolute or climbs out of `root` (``..``, symlinks).
    """
    root_p = Path(root).resolve()
    cand = (root_p / relative).resolve()
    if cand != root_p and root_p not in cand.parents:
        raise InputError(relative, f"output path escapes the output folder {root_p}")
    return cand


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to `path`; rename it to `path` on success.

    On any exception the temporary file is removed and `path` is untouched.
    The temporary name keeps the suffix(es) of `path`, so writers that pick a
    format from the extension (nibabel, trimesh, opensim) still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = "".join(path.suffixes)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".partial" + suffix, dir=path.parent)
    os.close(fd)
    os.chmod(tmp, _FILE_MODE)
    tmp_p = Path(tmp)
    try:
        yield tmp_p
        os.replace(tmp_p, path)
    except BaseException:
        tmp_p.unlink(missing_ok=True)
        raise


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Atomically write `text` (UTF-8) to `path`."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


@contextlib.contextmanager
def staged_dir(out: str | os.PathLike) -> Iterator[Path]:
    """Stage a whole result folder; publish it into `out` only on success.

    Yields an empty temporary folder beside `out`.  When the block ends without
    error every file in it is moved into `out` (created if needed; existing
    files of the same name are replaced one rename at a time).  On error the
    staging folder is deleted and `out` is left exactly as it was.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    try:
        yield stage
        out.mkdir(parents=True, exist_ok=True)
        for src in sorted(stage.rglob("*")):
            rel = src.relative_to(stage)
            dst = out / rel
            if src.is_dir():
                dst.mkdir(parents=True, exist_ok=True)
            else:
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.replace(src, dst)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
