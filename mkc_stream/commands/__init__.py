"""The subcommands, one module per group; :mod:`mkc_stream.cli` registers them in this order.

Each module listed here defines ``register(subparsers)``, which adds its parsers and sets
``func`` on them. What they share (exit codes, ``UsageError``, ``write_json``, ``Outputs``, the
--json/--quiet/--window options) lives in :mod:`.common`, below the commands and the cli; a command
never imports :mod:`mkc_stream.cli` (tests/test_layers.py checks it).
"""
COMMAND_MODULES: list[str] = [
    "mkc_stream.commands.calibrate",
    "mkc_stream.commands.ingest",
    "mkc_stream.commands.sim",
    "mkc_stream.commands.crosscheck",
    "mkc_stream.commands.inspect",
]
