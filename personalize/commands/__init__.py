"""One module per CLI command; each defines ``register(app: typer.Typer) -> None``.

The commands are thin: they parse options, call the library API and print.
"""
