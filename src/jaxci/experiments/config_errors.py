"""Where a config error is: YAML key paths to ``file:line``, duplicate keys, pydantic errors as one message.

Used by `jaxci.experiments.config` (loading) and `jaxci.experiments.runner` (the output folder's line); knows no schema.
"""

from __future__ import annotations

import typing
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel

from ..errors import ConfigError


class Locator:
    """Maps a key path of the YAML document to ``file:line`` through the `yaml.compose` node tree."""

    def __init__(self, path: Path, root):
        self.path, self.root = path, root

    def line(self, loc) -> int | None:
        node = self.root
        if node is None:
            return None
        line = node.start_mark.line + 1
        for key in loc:
            if isinstance(node, yaml.MappingNode):
                if isinstance(key, int):  # a single mapping given where a list is allowed
                    line = node.start_mark.line + 1
                    continue
                hit = [(k, v) for k, v in node.value if k.value == str(key)]
                if not hit:
                    break
                line, node = hit[-1][0].start_mark.line + 1, hit[-1][1]
            elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
                node = node.value[key]
                line = node.start_mark.line + 1
            else:
                break
        return line

    def error(self, loc, msg: str) -> ConfigError:
        line = self.line(loc)
        where = f"{self.path}:{line}" if line else f"{self.path}"
        return ConfigError(f"{where}: {format_loc(loc)}: {msg}" if loc else f"{where}: {msg}")


def format_loc(loc) -> str:
    """``('methods', 0, 'params', 'cohort')`` -> ``'methods[0].params.cohort'``."""
    out = ""
    for k in loc:
        out += f"[{k}]" if isinstance(k, int) else (f".{k}" if out else str(k))
    return out


def check_duplicates(node, locator: Locator, loc=()) -> None:
    if isinstance(node, yaml.MappingNode):
        seen = set()
        for k, v in node.value:
            if k.value in seen:
                raise ConfigError(f"{locator.path}:{k.start_mark.line + 1}: {format_loc((*loc, k.value))}: "
                                  f"duplicate key")
            seen.add(k.value)
            check_duplicates(v, locator, (*loc, k.value))
    elif isinstance(node, yaml.SequenceNode):
        for i, v in enumerate(node.value):
            check_duplicates(v, locator, (*loc, i))


def _model_at(root: type[BaseModel], loc) -> type[BaseModel] | None:
    """The pydantic model under `root` that holds the keys at `loc` (to list the allowed keys)."""
    model: Any = root
    for key in loc:
        if isinstance(key, int):
            continue
        field = model.model_fields.get(key) if model is not None else None
        if field is None:
            return None
        model = _inner_model(field.annotation)  # a pydantic model or None
    return model


def _inner_model(ann):
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return ann
    for a in typing.get_args(ann):
        m = _inner_model(a)
        if m is not None:
            return m
    return None


def pydantic_message(err: dict, root: type[BaseModel]) -> tuple[tuple, str]:
    """One pydantic error of a document validated by `root` as ``(key path, message)``: unknown keys with the
    allowed ones, a model validator's "field: message" moved onto that field, the offending input."""
    loc, typ = tuple(err["loc"]), err["type"]
    if typ == "extra_forbidden":
        model = _model_at(root, loc[:-1])
        allowed = f"; allowed keys: {', '.join(model.model_fields)}" if model else ""
        return loc, f"unknown key {loc[-1]!r}{allowed}"
    if typ == "missing":
        return loc, "required key is missing"
    msg = err["msg"].removeprefix("Value error, ")
    field, sep, rest = msg.partition(": ")
    model = _model_at(root, loc) if sep else None
    if model is not None and field in model.model_fields:  # a model validator naming the field at fault
        return (*loc, field), rest
    if typ not in ("value_error", "assertion_error") and "input" in err:
        msg += f" (got {err['input']!r})"
    return loc, msg
