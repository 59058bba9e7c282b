"""Dataclass configs: help text, layering of option values, config files.

Used by the CLI's flag generator (:mod:`plenoctree.cli._options`) and by the pipeline (stage
overrides); imports nothing heavy.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any

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
        setattr(cfg, key, value)
    return cfg


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
