"""Old home of :mod:`fepr.cli.compare`, kept so that ``from fepr.compare import compare`` (the Python entry
point its docs gave) still works. New code imports from :mod:`fepr.cli.compare`."""

from .cli.compare import CompareResult, compare, parse_size

__all__ = ["CompareResult", "compare", "parse_size"]
