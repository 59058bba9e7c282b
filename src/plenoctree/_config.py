"""Dataclass configs: help text, layering of option values, config files.

Used by the CLI's flag generator (:mod:`plenoctree.cli._options`) and by the pipeline (stage
overrides); imports nothing heavy.
"""

from __future__ import annotations

import dataclasses
import json
import re
import types
import typing
from pathlib import Path
from typing import Any

from ._bounds import bound_error, is_integer_type
from .errors import ConfigError

__all__ = ["apply", "field_help", "flag_name", "spell_flags", "load_config_file",
           "config_dict", "parse_background"]


def field_help(cls: type) -> dict[str, str]:
    """Help text of each field of dataclass ``cls``: ``metadata["help"]``, else the docstring
    written under the field (searched through the base classes)."""
    from .nerf.config import field_docs

    docs: dict[str, str] = {}
    for klass in reversed([c for c in cls.__mro__ if dataclasses.is_dataclass(c)]):
        try:
            docs.update(field_docs(klass))
        except (OSError, TypeError, IndexError, SyntaxError):  # pragma: no cover - no source
            pass
    for f in dataclasses.fields(cls):
        if "help" in f.metadata:
            docs[f.name] = str(f.metadata["help"])
    return docs


def parse_background(text: str) -> tuple[float, float, float]:
    """``white``, ``black``, ``R,G,B`` or one grey value, floats in [0, 1] -> an RGB tuple;
    anything else raises :class:`ConfigError`."""
    t = str(text).strip().lower()
    named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
    if t in named:
        return named[t]
    try:
        vals = tuple(float(v) for v in t.split(","))
    except ValueError:
        vals = ()
    if len(vals) == 1:
        vals = vals * 3
    if len(vals) != 3 or not all(0.0 <= v <= 1.0 for v in vals):
        raise ConfigError(f"--background: expected white, black or R,G,B in [0,1], got {text!r}")
    return vals  # type: ignore[return-value]


def flag_name(f: dataclasses.Field, prefix: str = "", flag: str | None = None) -> str:
    """The command-line flag of config field ``f``: ``--<prefix><name>`` with ``-`` for ``_``,
    or ``--<prefix><flag>`` (default: ``metadata["flag"]``); ``show_progress`` is
    ``--<prefix>progress``."""
    name = (flag or f.metadata.get("flag")
            or ("progress" if f.name == "show_progress" else f.name))
    return "--" + prefix + name.replace("_", "-")


_FIELD_NAMED = r"(?<![\w.-])(?:\w+(?::\s|\.))?([a-z][a-z0-9_]*)(?= (?:must|is required|exceeds))"
"""A field name as config checks write it: ``lr_decay must``, ``finetune: lr_decay must``,
``CompressOptions.bits must``."""


def spell_flags(message: str, flags: dict[str, str], dashed: dict[str, str] | None = None
                ) -> str:
    """An error ``message`` of a config check with its field names spelled as the flags the
    user typed: ``flags`` maps field names to flags (``{"lr_decay": "--finetune.lr-decay"}``),
    ``dashed`` other flags to the flags typed (``{"--grid": "--extract.grid"}``)."""
    if dashed:
        message = re.sub(r"(?<![\w.-])--[a-z0-9][a-z0-9-]*",
                         lambda m: dashed.get(m.group(0), m.group(0)), message)
    return re.sub(_FIELD_NAMED, lambda m: flags.get(m.group(1), m.group(0)), message)


def apply(cfg: Any, values: dict[str, Any], where: str = "config", _path: str = "") -> Any:
    """Set ``values`` (nested dicts for nested dataclasses) on dataclass ``cfg``; returns it.

    Unknown names raise :class:`ConfigError` naming ``where`` and the dotted key
    (``c.json: unknown option 'extract.gird'``); lists become tuples where the field's default
    is a tuple (JSON has no tuples); a ``background`` given as text (``white``, ``black``,
    ``R,G,B``) becomes its RGB tuple (:func:`parse_background`)."""
    names = {f.name: f for f in dataclasses.fields(cfg)}
    for key, value in values.items():
        if key not in names:
            raise ConfigError(f"{where}: unknown option {_path + key!r}; known: "
                              f"{', '.join(sorted(names))}")
        cur = getattr(cfg, key)
        if dataclasses.is_dataclass(cur) and isinstance(value, dict):
            apply(cur, value, where, f"{_path}{key}.")
            continue
        ann = str(names[key].type)
        if key == "background" and isinstance(value, str):
            value = parse_background(value)
        if isinstance(value, list) and (isinstance(cur, tuple) or ann.startswith("tuple")
                                        or key == "background"):
            value = tuple(value)
        check_value(type(cfg), names[key], value, where, _path + key)
        setattr(cfg, key, value)
    return cfg


def _type_ok(value: Any, tp: Any) -> bool:
    """Whether ``value`` fits the annotation ``tp`` (the types configs use; others pass)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any or tp is object:
        return True
    if tp is type(None):
        return value is None
    if origin in (typing.Union, types.UnionType):
        return any(_type_ok(value, a) for a in args)
    if origin is typing.Literal:
        return value in args
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if tp is str or tp is Path:
        return isinstance(value, (str, Path))
    if origin is tuple:
        if not isinstance(value, (tuple, list)):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_type_ok(v, args[0]) for v in value)
        return len(args) == len(value) and all(_type_ok(v, a) for v, a in zip(value, args))
    if origin in (list, dict) or tp in (list, dict):
        return isinstance(value, origin or tp)
    if dataclasses.is_dataclass(tp):
        return isinstance(value, tp)
    return True


def _type_words(tp: Any) -> str:
    names = {bool: "true or false", int: "an integer", float: "a number", str: "a string",
             Path: "a path", type(None): "null"}
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return " or ".join(_type_words(a) for a in typing.get_args(tp))
    if typing.get_origin(tp) is tuple:
        return f"a list of {len(typing.get_args(tp))} values"
    if typing.get_origin(tp) is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    return names.get(tp, getattr(tp, "__name__", str(tp)))


def check_value(cls: type, f: dataclasses.Field, value: Any, where: str, key: str = "") -> None:
    """ConfigError unless ``value`` fits field ``f`` of dataclass ``cls`` (its type annotation,
    its ``choices`` metadata and the ceilings of :mod:`._bounds`); the message names ``where``
    (the config file), the key (``key``: its dotted path, default the field's name) and, for a
    top-level key, the flag (``--steps`` for ``max_steps``)."""
    try:
        tp = typing.get_type_hints(cls)[f.name]
    except Exception:  # noqa: BLE001 - an annotation that cannot be resolved: no type check
        tp = Any
    key = key or f.name
    named = f"{key!r}" + ("" if "." in key else f" ({flag_name(f)})")
    if not _type_ok(value, tp):
        raise ConfigError(f"{where}: {named} must be {_type_words(tp)}, got {value!r}")
    choices = f.metadata.get("choices")
    if choices and value is not None and value not in choices:
        raise ConfigError(f"{where}: {named} must be one of "
                          f"{', '.join(map(str, choices))}, got {value!r}")
    problem = bound_error(f.name, value, is_integer_type(tp))
    if problem:
        raise ConfigError(f"{where}: {named} {problem}")


def load_config_file(path: str | Path | None) -> dict[str, Any]:
    """The options of ``--config FILE`` (``{}`` without one); bad files raise ConfigError."""
    if not path:
        return {}
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except OSError as e:
        raise ConfigError(f"{p}: cannot read the config file ({e.strerror})") from None
    except ValueError as e:
        raise ConfigError(f"{p}: not a JSON config file ({e})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: expected a JSON object of options, got {type(data).__name__}")
    return data


def config_dict(cfg: Any) -> dict[str, Any]:
    """A dataclass config as JSON-able dict (tuples as lists, paths as strings)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=str))
