"""Benchmarks behind ``fastgha bench TARGET``: one module per target (``render.py``, ...).

Each module defines ``run(args) -> dict`` (a JSON-serialisable result with a ``"summary"``
object of headline numbers) and optionally ``add_arguments(parser)`` for its own options.
``fastgha_core.commands.bench`` discovers them; adding a target touches no other file.
"""
