"""Output locations: checked before any work starts, replaced whole when the work succeeded.

Every command writes into one ``--out`` folder (``ik``: one ``.mot`` file).  Before
the command reads a byte of its inputs `check_output_dir` makes sure that

* ``--out`` is not an existing file (a folder is expected) and its folder can be
  written (a probe folder is created and removed there: permission bits alone
  say nothing for root, read-only mounts or immutable folders);
* ``--out`` is neither an input folder nor inside one, and holds no input (an
  input folder's contents would be mixed with, or replaced by, the results);
* an existing non-empty ``--out`` is only replaced with ``overwrite=True``
  (``--overwrite``); otherwise it is refused, so old files never sit beside new ones.

`replaced_dir` then stages the results in a sibling folder and, on success,
swaps it for ``--out`` in two renames (the old folder is deleted afterwards):
``--out`` holds exactly the new run's files, or on error exactly what it held
before.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterable, Iterator

from lowerlimb.errors import InputError

__all__ = ["check_output_dir", "check_output_file", "replaced_dir", "probe_writable"]


def _existing_ancestor(p: Path) -> Path:
    p = Path(os.path.abspath(p))
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def probe_writable(folder: Path, shown: Path | str) -> None:
    """Raise `InputError` naming `shown` unless a folder can be created in `folder` (its nearest existing ancestor)."""
    base = _existing_ancestor(folder)
    if not base.is_dir():
        raise InputError(shown, f"cannot be created: {base} is a file, not a folder")
    try:
        probe = tempfile.mkdtemp(prefix=".personalize-probe-", dir=base)
    except OSError as exc:
        raise InputError(shown, f"cannot write to {base} ({exc.strerror or exc})") from None
    os.rmdir(probe)


def _resolved(p) -> Path:
    return Path(os.path.realpath(os.path.abspath(p)))


def _check_inputs(out_r: Path, shown, inputs: Iterable) -> None:
    for inp in inputs:
        if inp is None:
            continue
        p = _resolved(inp)
        if p.is_dir() and (out_r == p or p in out_r.parents):
            raise InputError(shown, f"is {'the' if out_r == p else 'inside the'} input folder {inp}: "
                                    "choose an output folder outside the inputs")
        if out_r == p:
            raise InputError(shown, f"is the input {inp}")
        if out_r in p.parents:
            raise InputError(shown, f"contains the input {inp}: choose an output folder that holds no input")


def check_output_dir(out, *, inputs: Iterable = (), overwrite: bool = False, option: str = "--out") -> Path:
    """Check the output folder `out` before any work (see the module docstring); returns it as a Path.

    Parameters
    ----------
    out : path of the output folder (need not exist)
    inputs : paths of the input files and folders of the command
    overwrite : allow replacing an existing non-empty folder
    option : the option's name, for the messages

    Raises
    ------
    InputError
        `out` is an existing file, cannot be written, is or lies inside an input
        folder, contains an input, or is a non-empty folder without `overwrite`.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, f"{option} exists and is a file, not a folder")
    _check_inputs(_resolved(out), out, inputs)
    if out.is_dir():
        try:
            n = sum(1 for _ in out.iterdir())
        except OSError as exc:
            raise InputError(out, f"cannot list the folder ({exc.strerror or exc})") from None
        if n and not overwrite:
            raise InputError(out, f"{option} already holds {n} file(s) or folder(s) (an earlier run?): use --overwrite "
                                  "to replace it whole, or choose another folder")
    probe_writable(out.parent, out)
    return out


def check_output_file(out, *, inputs: Iterable = (), option: str = "--out") -> Path:
    """Check an output file path before any work: not a folder, not an input, its folder writable."""
    out = Path(out)
    if out.is_dir():
        raise InputError(out, f"{option} is an existing folder; give a file name")
    _check_inputs(_resolved(out), out, inputs)
    probe_writable(out.parent, out)
    return out


@contextlib.contextmanager
def replaced_dir(out) -> Iterator[Path]:
    """Stage a result folder beside `out`; on success `out` becomes exactly the staged folder.

    Yields an empty temporary folder.  When the block ends without error, an
    existing `out` is renamed aside, the stage renamed to `out` and the old
    folder deleted; on error the stage is deleted and `out` is untouched.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    old: Path | None = None
    try:
        yield stage
        os.chmod(stage, 0o777 & ~_UMASK)
        if out.exists() or out.is_symlink():
            if not out.is_dir():
                raise InputError(out, "exists and is a file, not a folder")
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.rmdir(old)
            os.replace(out, old)
        try:
            os.replace(stage, out)
        except BaseException:
            if old is not None:
                os.replace(old, out)
                old = None
            raise
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def _umask_now() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


_UMASK = _umask_now()  # read once: os.umask is process-wide and not thread-safe to toggle


@contextlib.contextmanager
def fresh_dir(out) -> Iterator[Path]:
    """Yield `out` as a new empty folder, the old one set aside; on error `out` gets its old content back.

    For work that must see its final paths while it runs (the demo's subject
    folder is named in its pipeline report); sub-folders should still be staged.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    old: Path | None = None
    if out.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
        os.rmdir(old)
        os.replace(out, old)
    try:
        out.mkdir()
        yield out
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        if old is not None:
            os.replace(old, out)
            old = None
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
