"""The ``personalize`` command line.

Each sub-command lives in ``personalize/commands/<name>.py`` and registers
itself on the shared Typer app.  Errors in user input (`InputError`) become a
single line on stderr and exit code 2; nothing else about the failure leaks out
as a traceback unless ``PERSONALIZE_DEBUG=1``.  Usage errors (unknown option, missing
argument) print click's usage text and exit 2; ``personalize`` alone prints the
help (exit 0); ``personalize --version`` prints the version.

Exit codes: 0 success, 1 some subjects of a batch failed (see batch.csv) or an
internal error, 2 bad input or usage, 130 interrupted (Ctrl-C, SIGINT), 143
terminated (SIGTERM).
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import sys

import typer

from . import __version__
from lowerlimb.errors import FitError, InputError, Interrupted

COMMANDS = (
    "phantom", "surfaces", "bones", "ik", "markers", "correlate",
    "run", "validate", "batch", "demo", "dynamics", "scale",
)

app = typer.Typer(
    name="personalize",
    help="Subject-specific lower-limb kinematic models from MRI and motion capture.",
    no_args_is_help=False,  # click >= 8.2 exits 2 on no_args_is_help; bare `personalize` is a request for help
    pretty_exceptions_enable=False,
    add_completion=False,
)


@app.callback(invoke_without_command=True)
def _root(ctx: typer.Context,
          version: bool = typer.Option(False, "--version", is_eager=True, help="Print the version and exit.")) -> None:
    """Subject-specific lower-limb kinematic models from MRI and motion capture."""
    if version:
        typer.echo(f"personalize {__version__}")
        raise typer.Exit(0)
    if ctx.invoked_subcommand is None:
        typer.echo(ctx.get_help())
        raise typer.Exit(0)


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
        rc = app(args=argv, standalone_mode=False, prog_name="personalize")
    except (InputError, FitError) as exc:
        # one line, whatever a library put in the message (a parser's multi-line text)
        typer.echo(f"error: {' '.join(str(exc).split())}", err=True)
        return 2
    except typer.Exit as exc:
        return exc.exit_code
    except Interrupted as exc:
        typer.echo(f"interrupted ({exc.signal_name}){exc.detail}", err=True)
        return exc.exit_code
    except (typer.Abort, KeyboardInterrupt):
        typer.echo("interrupted (SIGINT)", err=True)
        return 130
    except typer.TyperException as exc:
        # typer vendors click: its ClickException (usage errors, bad parameters) derives from TyperException
        show = getattr(exc, "show", None)
        if callable(show):
            show()
        else:
            typer.echo(f"error: {exc.format_message()}", err=True)
        return int(getattr(exc, "exit_code", 2))
    except OSError as exc:
        # file-system faults the commands did not foresee: still one line naming the file
        where = exc.filename or "output"
        typer.echo(f"error: {where}: {' '.join(str(exc.strerror or exc).split())}", err=True)
        return 2
    except Exception as exc:  # anything unexpected
        if os.environ.get("PERSONALIZE_DEBUG"):
            raise
        typer.echo(f"error: internal error ({type(exc).__name__}: {exc}); rerun with PERSONALIZE_DEBUG=1 for details", err=True)
        return 1
    return rc if isinstance(rc, int) else 0


def _console_main() -> None:  # pragma: no cover - thin wrapper
    from lowerlimb.errors import handle_termination

    handle_termination()
    sys.exit(main())


if __name__ == "__main__":  # pragma: no cover
    _console_main()
