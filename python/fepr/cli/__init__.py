"""The command-line tools: the ``fepr`` command and what its subcommands run.

- :mod:`~fepr.cli.commands`: the ``fepr`` command itself (parser, ``run``, ``mesh``, ``view``, exit codes);
  :func:`main` is the console entry point (``pyproject.toml``) and what ``python -m fepr`` calls.
- :mod:`~fepr.cli.demo`: ``fepr demo`` (the seed demos and the gallery).
- :mod:`~fepr.cli.compare`: ``fepr compare`` (one scene with and without FEPR, plots, video, report).
- :mod:`~fepr.cli.bench`: ``fepr bench`` (kernel and whole-step timings, one subprocess per scene).
- :mod:`~fepr.cli.progress`: the progress bar they share.

The command module is not named ``main`` so that ``fepr.cli.main`` is only ever the function.
"""

from .commands import EXIT_ERROR, EXIT_INVALID, EXIT_OK, EXIT_RUNAWAY, EXIT_STRICT, build_parser, main

__all__ = ["EXIT_ERROR", "EXIT_INVALID", "EXIT_OK", "EXIT_RUNAWAY", "EXIT_STRICT", "build_parser", "main"]
