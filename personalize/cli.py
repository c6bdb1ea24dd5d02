"""The ``personalize`` command line.

Each sub-command lives in ``personalize/commands/<name>.py`` and registers
itself on the shared Typer app.  Errors in user input (`InputError`) become a
single line on stderr and exit code 2; nothing else about the failure leaks out
as a traceback unless ``PERSONALIZE_DEBUG=1``.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import sys

import typer

from .errors import FitError, InputError

COMMANDS = (
    "phantom", "surfaces", "bones", "ik", "markers", "correlate",
    "run", "validate", "batch", "demo",
)

app = typer.Typer(
    name="personalize",
    help="Subject-specific lower-limb kinematic models from MRI and motion capture.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


def _register_commands() -> None:
    for name in COMMANDS:
        modname = f"personalize.commands.{name}"
        if importlib.util.find_spec(modname) is not None:
            importlib.import_module(modname).register(app)


_register_commands()


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    try:
        # without standalone mode click returns (not raises) the code of typer.Exit
        rc = app(args=argv, standalone_mode=False)
    except InputError as exc:
        typer.echo(f"error: {exc}", err=True)
        return 2
    except FitError as exc:
        typer.echo(f"error: {exc}", err=True)
        return 2
    except typer.Exit as exc:
        return exc.exit_code
    except (typer.Abort, KeyboardInterrupt):
        typer.echo("aborted", err=True)
        return 130
    except Exception as exc:  # click usage errors and anything unexpected
        import click

        if isinstance(exc, click.ClickException):
            exc.show()
            return exc.exit_code
        if os.environ.get("PERSONALIZE_DEBUG"):
            raise
        typer.echo(f"error: internal error ({type(exc).__name__}: {exc}); rerun with PERSONALIZE_DEBUG=1 for details", err=True)
        return 1
    return rc if isinstance(rc, int) else 0


def _console_main() -> None:  # pragma: no cover - thin wrapper
    sys.exit(main())


if __name__ == "__main__":  # pragma: no cover
    _console_main()
