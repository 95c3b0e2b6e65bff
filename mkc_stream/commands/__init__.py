"""Subcommands beyond `calibrate`, one module each.

Each module listed here defines ``register(subparsers)``, which adds its parsers and sets
``func`` on them.  Shared helpers (``UsageError``, ``write_json``, exit codes) live in
:mod:`mkc_stream.cli`; import them inside the command functions.
"""
COMMAND_MODULES: list[str] = [
    "mkc_stream.commands.ingest",
    "mkc_stream.commands.sim",
    "mkc_stream.commands.crosscheck",
]
