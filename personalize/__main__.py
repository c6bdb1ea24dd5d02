"""``python -m personalize``: the command line (guarded: multiprocessing's spawn re-imports this module)."""
from .cli import _console_main

if __name__ == "__main__":
    _console_main()
