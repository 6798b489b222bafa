"""The tree is a map: drivers import nothing of robotd, and robotd's subpackages import only downwards."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

LAYERS: tuple[tuple[str, ...], ...] = (
    ("robotd", "robotd.kinematics"),
    ("robotd.config",),
    ("robotd.logs",),
    ("robotd.estimation",),
    ("robotd.viz",),
    ("robotd.daemon", "robotd.fleet"),  # the fleet link is one of the daemon's tasks
    ("robotd.sim",),
    ("robotd.offline",),
    ("robotd.tools",),
    # the top: what a person runs (the command line), and the tools that measure and document it as it is run
    ("robotd.commands", "robotd.cli", "robotd.__main__", "robotd.tools.childguard", "robotd.bench", "robotd.readme"),
)
"""robotd's subpackages from the bottom up: a module may import its own layer and the layers below it."""


def module_name(path: Path) -> str:
    """The dotted module name of a source file in the repository."""
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def layer_of(module: str) -> int:
    """The index in LAYERS of the longest layer prefix of `module`."""
    best, best_len = -1, -1
    for index, names in enumerate(LAYERS):
        for name in names:
            if (module == name or module.startswith(name + ".")) and len(name) > best_len:
                best, best_len = index, len(name)
    return best


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """Every module a file imports (at any depth, function-level imports included), with the line number."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
            found.extend((node.lineno, f"{node.module}.{alias.name}") for alias in node.names)
    return found


SOURCES = sorted([*REPO.glob("robotd/**/*.py"), *REPO.glob("drivers/**/*.py")])


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(REPO)))
def test_imports_point_down_the_layers(path: Path) -> None:
    """drivers never import robotd; a robotd module never imports a layer above its own."""
    me = module_name(path)
    wrong: list[str] = []
    for line, target in imported_modules(path):
        if not target.startswith(("robotd", "drivers")):
            continue
        if me.startswith("drivers"):
            if target.split(".")[0] == "robotd":
                wrong.append(f"line {line}: {target} (drivers take plain arguments, not robotd's)")
            continue
        if target.startswith("drivers"):
            continue
        mine, theirs = layer_of(me), layer_of(target)
        assert mine >= 0, f"{me} is in no layer: add it to LAYERS"
        if theirs > mine:
            wrong.append(f"line {line}: {target} (layer {LAYERS[theirs][0]} is above {LAYERS[mine][0]})")
    assert not wrong, f"{me} imports upwards:\n" + "\n".join(wrong)


def test_every_module_is_in_a_layer() -> None:
    """A new robotd subpackage must be placed in the map before it is used."""
    unplaced = [module_name(p) for p in SOURCES if module_name(p).startswith("robotd") and layer_of(module_name(p)) < 0]
    assert not unplaced


def test_the_layer_check_sees_an_upward_import(tmp_path: Path) -> None:
    """The checker itself: an estimation module importing the daemon is found."""
    source = tmp_path / "probe.py"
    source.write_text("def f():\n    from robotd.daemon import service\n", encoding="utf-8")
    targets = [t for _, t in imported_modules(source)]
    assert "robotd.daemon.service" in targets
    assert layer_of("robotd.daemon.service") > layer_of("robotd.estimation.ekf")
