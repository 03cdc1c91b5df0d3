"""``PATH=VALUE`` settings of a nerfstudio config, as the benchmarks take them (``--overrides
pipeline.revert.enabled=False``): one setting changed on the command line, typed like the field it replaces."""

from __future__ import annotations

import json
from dataclasses import fields, is_dataclass
from typing import Any, Sequence

_TRUE, _FALSE = ("true", "1", "yes", "on"), ("false", "0", "no", "off")


def parse_like(text: str, current: Any, path: str) -> Any:
    """``text`` read as a value of the type of ``current`` (bool, int, float, str, tuple or list; None: JSON, else
    the text itself).

    Raises:
        ValueError: when ``text`` is not such a value (the message names ``path``).
    """
    try:
        if isinstance(current, bool):
            if text.lower() in _TRUE:
                return True
            if text.lower() in _FALSE:
                return False
            raise ValueError("expected True or False")
        if isinstance(current, int):
            return int(text)
        if isinstance(current, float):
            return float(text)
        if isinstance(current, (tuple, list)):
            value = json.loads(text)
            if not isinstance(value, list):
                raise ValueError("expected a JSON list, e.g. [0, 0, 1]")
            return type(current)(value)
        if current is None:
            try:
                return json.loads(text)
            except json.JSONDecodeError:
                return text
        if isinstance(current, str):
            return text
    except ValueError as exc:
        raise ValueError(f"{path}={text}: {exc}") from None
    raise ValueError(f"{path}: a {type(current).__name__} cannot be set from the command line")


def apply_overrides(config: Any, overrides: Sequence[str]) -> Any:
    """Sets each ``PATH=VALUE`` of ``overrides`` on ``config`` (a dataclass; ``PATH`` is dotted, e.g.
    ``pipeline.registration.upright``, and goes through dicts by key, e.g.
    ``optimizers.features_rest.optimizer.lr``) in place, and returns ``config``.

    Raises:
        ValueError: for an item without ``=``, a path that names no field (the message lists the fields of the
            last dataclass it reached), a field that holds a dataclass, or a value of the wrong type.
    """
    for item in overrides:
        path, sep, text = item.partition("=")
        path = path.strip()
        if not sep or not path:
            raise ValueError(f"override {item!r} is not PATH=VALUE (e.g. pipeline.revert.enabled=False)")
        target = config
        parts = path.split(".")
        for depth, name in enumerate(parts):
            names = _names(target)
            if name not in names:
                where = ".".join(parts[:depth]) or "the config"
                raise ValueError(f"override {path}: {where} has no field {name!r}; its fields: {', '.join(names)}")
            if depth < len(parts) - 1:
                target = _get(target, name)
        current = _get(target, parts[-1])
        if is_dataclass(current) or isinstance(current, dict):
            raise ValueError(f"override {path}: a group of settings; name one of its fields "
                             f"({', '.join(_names(current))})")
        value = parse_like(text.strip(), current, path)
        if isinstance(target, dict):
            target[parts[-1]] = value
        else:
            setattr(target, parts[-1], value)
    return config


def _names(node: Any) -> list:
    """The fields of a dataclass or the keys of a dict (nerfstudio's ``optimizers``), else none."""
    if is_dataclass(node):
        return [f.name for f in fields(node)]
    return [str(k) for k in node] if isinstance(node, dict) else []


def _get(node: Any, name: str) -> Any:
    return node[name] if isinstance(node, dict) else getattr(node, name)
