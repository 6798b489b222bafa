"""YAML text to plain data for a configuration: no tags, no aliases, bounded nesting, one-line errors.

Aliases are refused outright: an alias is a pointer, and a few nested ones ("billion laughs") describe a structure
of billions of elements that any walk over the data (the schema's) must visit. A configuration never needs one.
Explicit tags are refused too (none is needed, and some of PyYAML's safe constructors raise bare exceptions on a
badly tagged value). Nesting is bounded because the composer recurses once per level.
"""

from __future__ import annotations

import typing
from typing import Any

import yaml
from yaml.composer import ComposerError
from yaml.nodes import Node

from robotd.config.schema import ConfigError

MAX_DEPTH = 32  # robotd's deepest key is 4 levels down, a list of lists 2 more


class _ConfigLoader(yaml.SafeLoader):
    """PyYAML's safe loader that refuses alias events, explicit tags and nesting deeper than MAX_DEPTH."""

    depth = 0

    def compose_node(self, parent: Node | None, index: int) -> Node | None:
        event: Any = typing.cast(Any, self).peek_event()  # PyYAML's stubs leave peek_event untyped
        if self.check_event(yaml.AliasEvent):
            problem = "aliases (*name) are not accepted in a configuration: write the value out"
            raise ComposerError(None, None, problem, event.start_mark)
        if getattr(event, "tag", None) is not None:  # some of PyYAML's constructors crash on a bad tagged value
            problem = "tags (!name, !!name) are not accepted in a configuration"
            raise ComposerError(None, None, problem, event.start_mark)
        if self.depth >= MAX_DEPTH:
            raise ComposerError(None, None, f"nested deeper than {MAX_DEPTH} levels", event.start_mark)
        self.depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1


def parse_yaml(text: str, source: str) -> Any:
    """The data of one YAML document, or ConfigError with one line naming `source` and where it went wrong."""
    loader = _ConfigLoader(text)
    try:
        return loader.get_single_data()
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(error, "problem", None) or str(error)
        raise ConfigError([f"{source}: invalid YAML{where}: {problem}"]) from None
    except (ValueError, OverflowError) as error:  # PyYAML lets a bad date or an endless integer through unwrapped
        reason = str(error).split(": value has")[0]  # Python's integer message goes on to advise on its own API
        raise ConfigError([f"{source}: invalid YAML: {reason}"]) from None
    finally:
        loader.dispose()
