#!/usr/bin/env python3
"""Fail on an import loop between fepr-core's top-level modules.

A top-level module is a file `src/name.rs` or a folder `src/name/`. Module `a` depends on `b` where code of `a`
(tests excluded: everything from a `#[cfg(test)]` line on) names `crate::b`, in a `use` or in a path. The
dependencies must form no cycle: `docs/architecture.md` lists the layers and their order.

    python3 tools/check_import_loops.py [path/to/crates/fepr-core/src]

Exit status 0 without a loop, 1 with one (each loop printed with one example line per edge).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Dict, List, Set, Tuple

ROOT = Path(__file__).resolve().parents[1] / "crates" / "fepr-core" / "src"
# `crate::name` anywhere, and the names inside `use crate::{a, b::c}`.
PATH = re.compile(r"\bcrate::([a-z_][a-z0-9_]*)")
GROUP = re.compile(r"\bcrate::\{([^}]*)\}", re.S)


def top_module(src: Path, file: Path) -> str:
    rel = file.relative_to(src)
    return rel.parts[0][: -len(".rs")] if len(rel.parts) == 1 else rel.parts[0]


def code_lines(text: str) -> List[Tuple[int, str]]:
    """The file's lines up to its tests, with line comments removed."""
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        if line.strip().startswith("#[cfg(test)]"):
            break
        out.append((n, line.split("//", 1)[0]))
    return out


def dependencies(src: Path) -> Dict[str, Dict[str, str]]:
    """For every top-level module, the modules it names, each with one `file:line` where it does."""
    deps: Dict[str, Dict[str, str]] = {}
    for file in sorted(src.rglob("*.rs")):
        module = top_module(src, file)
        if module in ("lib", "main"):
            continue
        edges = deps.setdefault(module, {})
        lines = code_lines(file.read_text())
        text = "\n".join(line for _, line in lines)
        names: List[Tuple[str, int]] = []
        for m in PATH.finditer(text):
            names.append((m.group(1), text.count("\n", 0, m.start())))
        for m in GROUP.finditer(text):
            for part in m.group(1).split(","):
                name = part.strip().split("::")[0].strip()
                if name:
                    names.append((name, text.count("\n", 0, m.start())))
        for name, index in names:
            if name != module and name not in edges:
                edges[name] = f"{file.relative_to(src.parent.parent.parent)}:{lines[index][0]}"
    return deps


def cycles(deps: Dict[str, Dict[str, str]]) -> List[List[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    stack: List[str] = []
    on: Set[str] = set()
    out: List[List[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in deps.get(v, {}):
            if w not in deps:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(deps):
        if v not in index:
            visit(v)
    return out


def main(argv: List[str]) -> int:
    src = Path(argv[1]) if len(argv) > 1 else ROOT
    deps = dependencies(src)
    loops = cycles(deps)
    if not loops:
        print(f"no import loop between the {len(deps)} top-level modules of {src}")
        return 0
    for comp in loops:
        print(f"import loop between: {', '.join(comp)}")
        for a in comp:
            for b, where in sorted(deps[a].items()):
                if b in comp:
                    print(f"  {a} -> {b}  ({where})")
    return 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
