"""The README's generated blocks: text between `<!-- NAME:start -->` and `<!-- NAME:end -->` comes from a source.

Figures in the README are never typed in: each block is the output of a command in the repository (the
configuration reference from the schema, the results table from `robotd experiment`, the benchmark report from
`robotd bench --report`), spliced in by `robotd readme --update`; a test fails when a block is stale.
"""

from __future__ import annotations

import ast
from collections.abc import Callable
from pathlib import Path

from robotd.config.model import config_reference


def _file(path: str) -> Callable[[Path], str]:
    def read(root: Path) -> str:
        source = root / path
        if not source.exists():
            return f"*(not generated yet: `{path}` is missing)*\n"
        return source.read_text(encoding="utf-8")

    return read


def module_map(root: Path) -> str:
    """Every module of the two packages with the first line of its docstring: the architecture as it is."""
    lines = ["```"]
    for package in ("robotd", "drivers"):
        for path in sorted((root / package).rglob("*.py")):
            if path.name == "__main__.py":
                continue
            tree = ast.parse(path.read_text(encoding="utf-8"))
            summary = " ".join((ast.get_docstring(tree) or "").strip().split("\n\n")[0].split())
            name = path.relative_to(root).as_posix()
            lines.append(f"{name:34s} {summary}".rstrip())
    lines.append("```")
    return "\n".join(lines) + "\n"


def _imports(path: Path) -> set[str]:
    """The robotd and drivers modules a source file imports, at any depth (`from a import b` counts as a.b)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return {name for name in found if name.split(".")[0] in ("robotd", "drivers")}


def import_map(root: Path) -> str:
    """Which parts of the tree each subpackage imports: the layers as the code has them, not as they were drawn."""
    parts = sorted(
        ".".join(path.parent.relative_to(root).parts)
        for package in ("drivers", "robotd")
        for path in (root / package).glob("*/__init__.py")
    )

    def part_of(module: str) -> str | None:
        return next((part for part in parts if module == part or module.startswith(part + ".")), None)

    modules = {".".join(p.relative_to(root).with_suffix("").parts) for p in root.glob("*/**/*.py")}
    lines = ["```"]
    for part in parts:
        used: set[str] = set()
        for path in sorted((root / part.replace(".", "/")).rglob("*.py")):
            for imported in _imports(path):
                module = imported
                while module not in modules and f"{module}.__init__" not in modules and "." in module:
                    module = module.rsplit(".", 1)[0]  # `from a.b import Name`: the module is a.b
                used.add(part_of(module) or module)
        others = sorted(u.replace(".", "/") for u in used - {part})
        lines.append(f"{part.replace('.', '/') + '/':20s} -> {', '.join(others) or '(nothing of robotd or drivers)'}")
    lines.append("```")
    return "\n".join(lines) + "\n"


# block name -> how to produce its content from the repository root
BLOCKS: dict[str, Callable[[Path], str]] = {
    "modules": module_map,
    "imports": import_map,
    "config-reference": lambda _root: config_reference(),
    "results": _file("docs/results/results.md"),
    "scorecard": _file("docs/scorecard/sim/summary.md"),
    "scorecard-lab": _file("docs/scorecard/sim-lab/summary.md"),
    "scorecard-heldout": _file("docs/scorecard/sim-heldout/summary.md"),
    "scorecard-lab-heldout": _file("docs/scorecard/sim-lab-heldout/summary.md"),
    "scorecard-other": _file("docs/scorecard/sim-other/summary.md"),
    "bench": _file("docs/bench.md"),
}


def markers(name: str) -> tuple[str, str]:
    """The start and end comment lines of a block."""
    return f"<!-- {name}:start -->", f"<!-- {name}:end -->"


def splice(text: str, name: str, content: str) -> str:
    """`text` with the block `name` replaced by `content`; ValueError when the markers are missing."""
    start, end = markers(name)
    head, found_start, rest = text.partition(start)
    _, found_end, tail = rest.partition(end)
    if not found_start or not found_end:
        raise ValueError(f"no {start} ... {end} block")
    body = content if content.endswith("\n") else content + "\n"
    return f"{head}{start}\n{body}{end}{tail}"


def current(text: str, root: Path) -> str:
    """The README text with every generated block brought up to date."""
    for name, produce in BLOCKS.items():
        text = splice(text, name, produce(root))
    return text
