"""The documents say what the code does: the command-line synopses (docs/scenes.md and the CLI module's docstring)
list every command and option the parser has, the demo's section names every scene of the gallery, and the scene
file reference names every section and key the parser reads."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from fepr.cli import commands
from fepr.cli.demo import GALLERY
from fepr.scene import SCENE_KEYS

ROOT = Path(__file__).resolve().parent.parent
SCENES_MD = (ROOT / "docs" / "scenes.md").read_text(encoding="utf-8")


def _subcommands():
    parser = commands.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


def _synopsis(text: str) -> dict:
    """``{command: the synopsis text of its lines}`` from a block of ``fepr COMMAND ...`` lines."""
    out: dict = {}
    current = None
    for line in text.splitlines():
        m = re.match(r"\s*fepr (\w+)", line)
        if m:
            current = m.group(1)
            out[current] = out.get(current, "") + " " + line
        elif current and line.strip().startswith("["):
            out[current] += " " + line
        else:
            current = None
    return out


def _docs_block() -> str:
    section = SCENES_MD.split("## The command line", 1)[1]
    return section.split("```", 2)[1]


@pytest.mark.parametrize("where", ["docs/scenes.md", "fepr.cli.commands"])
def test_every_command_and_option_is_in_the_synopsis(where):
    text = _docs_block() if where == "docs/scenes.md" else commands.__doc__.split("Commands::", 1)[1]
    synopsis = _synopsis(text)
    for name, parser in _subcommands().items():
        assert name in synopsis, f"{where}: no synopsis line for `fepr {name}`"
        for action in parser._actions:
            if action.help == argparse.SUPPRESS or isinstance(action, argparse._HelpAction):
                continue
            if action.option_strings:
                assert any(re.search(rf"{o}\b", synopsis[name]) for o in action.option_strings), (
                    f"{where}: `fepr {name}` lacks {action.option_strings[-1]}"
                )


def test_the_demo_section_names_every_gallery_scene_and_option():
    section = SCENES_MD.split("### `fepr demo`", 1)[1].split("\n### ", 1)[0]
    for item in GALLERY:
        assert f"`{item.name}`" in section, item.name
    for action in _subcommands()["demo"]._actions:
        longs = [o for o in action.option_strings if o.startswith("--") and o != "--help"]
        if longs and action.help != argparse.SUPPRESS:
            assert f"`{longs[0]}" in section, longs[0]


def test_every_scene_section_and_key_is_documented():
    for section, keys in SCENE_KEYS.items():
        assert f"[{section}]" in SCENES_MD or f"[[{section}]]" in SCENES_MD, section
        for key in keys:
            assert f"`{key}`" in SCENES_MD, f"[{section}] {key}"
