"""The package's imports go one way (docs/design.md): core <- raster <- data <- train <- eval <-
scene, sfm, synth, sim <- transport, localize <- experiments <- commands / cli. Every import
statement counts, at module level or inside a function (a function-local import hides a cycle
from Python, not from this test)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "ghsplat_jax"

# Lower numbers are lower layers; a module may import its own layer's (without a cycle) or
# lower ones. The top-level helpers (io_utils, curves, paths, config_values, host_memory) sit below
# everything. The package root (ghsplat_jax/__init__.py) is the public facade: only commands may import it.
LAYERS = {
    "io_utils": 0, "curves": 0, "paths": 0, "config_values": 0, "host_memory": 0,
    "core": 1,
    "raster": 2,
    "data": 3,
    "train": 4,
    "eval": 5,
    "scene": 6, "sfm": 6, "synth": 6, "sim": 6,
    "transport": 7, "localize": 7,
    "experiments": 8,
    "commands": 9, "cli": 9, "__init__": 9,
}
# Genuine exceptions, each with its reason: (importing part, imported part) -> reason.
EXCEPTIONS: dict[tuple[str, str], str] = {}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def part_of(module: str) -> str:
    """The subpackage or top-level module of `ghsplat_jax.X...` ("__init__" for the root)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def imported(path: Path, known: set[str]) -> list[tuple[str, int]]:
    """(package module imported, line) for every import statement of the file, at any depth.
    `from a.b import c` counts as a.b.c when that is a module, else as a.b."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}:{node.lineno}: relative import (the package uses absolute ones)"
            for a in node.names:
                full = f"{node.module}.{a.name}"
                out.append((full if full in known else node.module, node.lineno))
    return [(m, line) for m, line in out if m == "ghsplat_jax" or m.startswith("ghsplat_jax.")]


def import_graph() -> dict[str, list[tuple[str, int]]]:
    mods = modules()
    return {m: imported(p, set(mods)) for m, p in mods.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of a directed graph (as a closed path), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (found := visit(start)):
            return found
    return None


def test_every_part_has_a_layer():
    assert {part_of(m) for m in modules() if m != "ghsplat_jax"} | {"__init__"} == set(LAYERS)


def test_no_upward_imports():
    upward = []
    for mod, targets in import_graph().items():
        src = part_of(mod)
        for target, line in targets:
            dst = part_of(target)
            if src != dst and LAYERS[dst] > LAYERS[src] and (src, dst) not in EXCEPTIONS:
                upward.append(f"{mod}:{line} imports {target} ({src} is below {dst})")
    assert not upward, "\n".join(upward)


def test_no_two_parts_import_each_other():
    parts: dict[str, set[str]] = {}
    for mod, targets in import_graph().items():
        parts.setdefault(part_of(mod), set()).update(part_of(t) for t, _ in targets if part_of(t) != part_of(mod))
    assert find_cycle(parts) is None, " -> ".join(find_cycle(parts))


def test_no_circular_module_imports():
    graph = {mod: {t for t, _ in targets if t != mod} for mod, targets in import_graph().items()}
    cycle = find_cycle(graph)
    assert cycle is None, " -> ".join(cycle)


@pytest.mark.parametrize("graph, cycle", [({"a": {"b"}, "b": {"c"}, "c": {"a"}}, True),
                                          ({"a": {"b", "c"}, "b": {"c"}, "c": set()}, False)])
def test_the_cycle_finder_finds_cycles(graph, cycle):
    assert (find_cycle(graph) is not None) == cycle
