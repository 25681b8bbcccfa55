"""A scene (a dict of TOML sections) written back as TOML text, so that every run of a sweep has a scene file
that ``fepr run`` runs on its own.

Only what scene files hold is written: tables of strings, numbers, booleans, lists and inline tables, and the
``[[bodies]]`` array of tables. Floats are written in Python's shortest round-trip form (``repr``), so that
reading the text back gives the same bits; ``inf`` and ``nan`` are TOML floats too. Nested tables are written
inline (``pin_below = { axis = "z", value = 1e-06 }``), which keeps the writer small and the file readable.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any, Mapping

from ..errors import ConfigError

__all__ = ["scene_toml"]

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def _key(k: str) -> str:
    return k if _BARE_KEY.fullmatch(k) else json.dumps(k)


def _value(v: Any, where: str) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)  # shortest text that round-trips, e.g. 0.1, 1e-05, 1000.0
    if isinstance(v, str):
        # A JSON string is a TOML basic string (the same escapes; JSON's \uXXXX is TOML's too).
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x, where) for x in v) + "]"
    if isinstance(v, Mapping):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x, where)}" for k, x in v.items()) + " }" if v else "{}"
    raise ConfigError(f"{where}: a scene value must be a string, number, boolean, list or table, got {v!r}")


def scene_toml(scene: Mapping[str, Any], header: str = "") -> str:
    """The TOML text of a scene given as a dict of sections (as :func:`fepr.scene.scene_from_dict` takes it).

    ``header`` is written first as ``#`` comment lines. Sections are ``[name]`` tables in the dict's order;
    ``bodies`` (a list of tables) is written as ``[[bodies]]`` entries after them.
    """
    lines = [f"# {line}".rstrip() for line in header.splitlines()]
    if lines:
        lines.append("")
    for name, section in scene.items():
        if name == "bodies":
            continue
        if not isinstance(section, Mapping):
            raise ConfigError(f"[{name}] must be a table of keys, got {section!r}")
        lines.append(f"[{_key(name)}]")
        lines.extend(f"{_key(k)} = {_value(v, f'[{name}] {k}')}" for k, v in section.items())
        lines.append("")
    for k, body in enumerate(scene.get("bodies", ()), 1):
        lines.append("[[bodies]]")
        lines.extend(f"{_key(key)} = {_value(v, f'[[bodies]] #{k} {key}')}" for key, v in body.items())
        lines.append("")
    return "\n".join(lines)
