"""Parameter paths: which value of a scene a sweep varies, checked against the scene format, and set in a copy.

A path is the scene's section and key joined by dots, as the scene file nests them: ``material.youngs_modulus``,
``integrator.dt``, ``initial.angular_velocity``, ``projection.enabled``. Deeper paths index lists of tables by
position, counted from 0: ``world.obstacles.0.friction``, ``bodies.1.material.youngs_modulus``, and a vector's
component: ``initial.velocity.2``. A path that names a whole section (``mesh``, ``material``) replaces that
section with a table, which is how a sweep picks a mesh from a list.

:func:`check_path` validates a path against the base scene before anything runs, with an error that names the
key and lists the keys that exist there; :func:`set_path` sets a value in a scene dict.
"""

from __future__ import annotations

import copy
from typing import Any, Callable, Dict, List, Mapping, Sequence, Tuple, Union

from ..errors import ConfigError
from ..scene.schema import (
    BODY_KEYS,
    KINEMATIC_PIN_KEYS,
    OBSTACLE_COMMON_KEYS,
    OBSTACLE_KEYS,
    OBSTACLE_MOTION_KEYS,
    SCENE_KEYS,
    SELF_CONTACT_KEYS,
    TERRAIN_KEYS,
)

__all__ = ["ParamPath", "SWEEPABLE_SECTIONS", "check_path", "ordered", "parse_path", "path_text", "set_path"]

#: A parsed path: section and key names, and list positions (ints).
ParamPath = Tuple[Union[str, int], ...]

#: Sections a sweep may vary (``[scene]`` only names the run; ``[export]`` is replaced by the sweep's own frames).
SWEEPABLE_SECTIONS: Tuple[str, ...] = (
    "mesh",
    "material",
    "mass",
    "initial",
    "integrator",
    "projection",
    "world",
    "run",
)
_BODY_SECTIONS = ("mesh", "material", "mass", "initial")
_BELOW_KEYS = ("axis", "value")


def _obstacle_keys(node: Any) -> Tuple[str, ...]:
    kind = str(node.get("type", "")).lower() if isinstance(node, Mapping) else ""
    return OBSTACLE_COMMON_KEYS + OBSTACLE_KEYS.get(kind, ())


# Keys of the tables inside a scene, by where they sit ("#" a list position). A table not listed here may only be
# entered where the base scene has the key (the scene's own validation then checks the value).
_KNOWN: Dict[Tuple[str, ...], Union[Tuple[str, ...], Callable[[Any], Tuple[str, ...]]]] = {
    ("world", "obstacles", "#"): _obstacle_keys,
    ("world", "obstacles", "#", "motion"): OBSTACLE_MOTION_KEYS,
    ("world", "obstacles", "#", "terrain"): TERRAIN_KEYS,
    ("world", "kinematic_pins", "#"): KINEMATIC_PIN_KEYS,
    ("world", "kinematic_pins", "#", "below"): _BELOW_KEYS,
    ("world", "pin_below"): _BELOW_KEYS,
    ("world", "self_contact"): SELF_CONTACT_KEYS,
    ("bodies", "#"): BODY_KEYS,
    ("bodies", "#", "pin_below"): _BELOW_KEYS,
    ("bodies", "#", "kinematic_pins", "#"): KINEMATIC_PIN_KEYS,
    ("bodies", "#", "kinematic_pins", "#", "below"): _BELOW_KEYS,
    ("bodies", "#", "self_contact"): SELF_CONTACT_KEYS,
    **{(s,): SCENE_KEYS[s] for s in SWEEPABLE_SECTIONS},
    **{("bodies", "#", s): SCENE_KEYS[s] for s in _BODY_SECTIONS},
}


def path_text(path: ParamPath) -> str:
    return ".".join(str(p) for p in path)


def parse_path(text: str, err: Callable[[str], ConfigError]) -> ParamPath:
    """``"world.obstacles.0.friction"`` -> ``("world", "obstacles", 0, "friction")``."""
    if not isinstance(text, str) or not text.strip():
        raise err(f"a parameter path must be a dotted name such as 'material.youngs_modulus', got {text!r}")
    out: List[Union[str, int]] = []
    for part in text.strip().split("."):
        if not part:
            raise err(f"parameter {text!r}: empty name between dots")
        out.append(int(part) if part.isdigit() else part)
    return tuple(out)


def check_path(path: ParamPath, base: Mapping[str, Any], err: Callable[[str], ConfigError]) -> None:
    """Raise ``err(message)`` unless ``path`` names a value of the base scene (``base``, its dict of sections) that
    a sweep may vary. The message names the path and the key that is wrong, and lists the keys known there."""
    name = path_text(path)
    head = path[0]
    multibody = "bodies" in base
    if head in ("scene", "export"):
        why = "it only names the run" if head == "scene" else "the sweep writes its own frames ([sweep] frames_every)"
        raise err(f"parameter {name!r}: [{head}] cannot be varied ({why})")
    if head == "run" and path[1:2] == ("threads",):
        raise err(
            f"parameter {name!r}: threads are set by the sweep ([sweep] cpus_per_run); results are bit-identical "
            "for any thread count"
        )
    if head == "bodies":
        if not multibody:
            raise err(f"parameter {name!r}: the base scene has no [[bodies]] (vary its sections directly)")
    elif head not in SWEEPABLE_SECTIONS:
        raise err(f"parameter {name!r}: unknown section {head!r} (known: {', '.join(SWEEPABLE_SECTIONS)}, bodies)")
    elif multibody and head in _BODY_SECTIONS:
        raise err(f"parameter {name!r}: the base scene has [[bodies]]; vary bodies.<position>.{head}... instead")
    node: Any = base
    pattern: List[str] = []
    for k, part in enumerate(path):
        where = path_text(path[:k]) or "the scene"
        if isinstance(part, int):
            if not isinstance(node, list):
                raise err(f"parameter {name!r}: {where} is not a list in the base scene, so {part} is no position")
            if part >= len(node):
                raise err(f"parameter {name!r}: {where} has {len(node)} entries in the base scene (positions from 0)")
            node = node[part]
            pattern.append("#")
            continue
        known = _KNOWN.get(tuple(pattern))
        if callable(known):
            known = known(node)
        if known is not None and k > 0:
            if part not in known:
                raise err(f"parameter {name!r}: unknown key {part!r} in {where} (known: {', '.join(known)})")
        elif k > 0 and not (isinstance(node, Mapping) and part in node):
            have = ", ".join(node) if isinstance(node, Mapping) else "nothing to index"
            raise err(f"parameter {name!r}: {where} has no key {part!r} in the base scene (it has: {have})")
        node = node.get(part) if isinstance(node, Mapping) else None
        pattern.append(part)


def set_path(scene: Dict[str, Any], path: ParamPath, value: Any) -> None:
    """Set ``value`` (a deep copy) at ``path`` in ``scene``, creating tables that the base scene leaves out."""
    node: Any = scene
    for k, part in enumerate(path[:-1]):
        nxt = path[k + 1]
        if isinstance(part, int):
            node = node[part]
            continue
        if part not in node or node[part] is None:
            node[part] = [] if isinstance(nxt, int) else {}
        node = node[part]
    node[path[-1]] = copy.deepcopy(value)


def ordered(assignments: Sequence[Tuple[ParamPath, Any]]) -> List[Tuple[ParamPath, Any]]:
    """Assignments in the order they are applied: shorter paths first (a whole ``mesh`` table, then
    ``mesh.resolution`` in it), otherwise as given."""
    return sorted(assignments, key=lambda a: len(a[0]))
