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


# block name -> how to produce its content from the repository root
BLOCKS: dict[str, Callable[[Path], str]] = {
    "modules": module_map,
    "config-reference": lambda _root: config_reference(),
    "results": _file("docs/results/results.md"),
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
