"""Config dataclass → command-line flags: the one mechanism every command uses.

A command describes its options as a dataclass (``TrainConfig``, ``ExtractConfig``,
``FinetuneConfig``, ``EvalConfig``, ``PipelineConfig``...). :func:`add_config` turns every
field into a flag; a new field becomes a flag with no other edit:

- flag ``--<prefix><field-name>`` (``_`` → ``-``), e.g. ``--batch-rays`` or, for a nested stage
  config of ``run``, ``--finetune.batch-rays``; the parsed value lands at dest
  ``<prefix><field_name>`` (``finetune.batch_rays``);
- help = the docstring under the field (or its ``metadata["help"]``), followed by the real
  default (``default: 0.01``; nothing when the default is ``None``/empty and the text says
  what happens then);
- type from the annotation: ``bool`` → ``--x/--no-x``; ``int``/``float``/``str`` (``| None``
  allowed); tuples of numbers → ``A,B,C``; a field named ``background`` → ``white``,
  ``black`` or ``R,G,B``;
- field metadata (``field(metadata={...})``) may add ``"choices"``, ``"flag"`` (another flag
  name, e.g. ``"steps"``), ``"positional": True``, ``"cli": False`` (no flag), ``"metavar"``.

Flags default to "not given" (``None``), so values layer: the dataclass default or preset, then
``--config FILE`` (JSON, the ``config.json`` a run saves), then the flags given. :func:`given`
collects what was given (nested by prefix); :func:`apply` sets it on a config, checking names.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
from pathlib import Path
from typing import Any, Iterable

from ..errors import ConfigError

__all__ = ["add_config", "given", "apply", "field_help", "load_config_file", "parse_background",
           "add_config_file", "config_to_json", "format_default"]


def field_help(cls: type) -> dict[str, str]:
    """Help text of each field of dataclass ``cls``: ``metadata["help"]``, else the docstring
    written under the field (searched through the base classes)."""
    from ..nerf.config import field_docs

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
    """``white``, ``black`` or ``R,G,B`` in [0, 1]."""
    t = str(text).strip().lower()
    if t == "white":
        return (1.0, 1.0, 1.0)
    if t == "black":
        return (0.0, 0.0, 0.0)
    try:
        vals = tuple(float(v) for v in t.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 3 or not all(0.0 <= v <= 1.0 for v in vals):
        raise argparse.ArgumentTypeError(
            f"expected white, black or R,G,B with values in [0, 1], got {text!r}")
    return vals  # type: ignore[return-value]


def _numbers(kind: type):
    def parse(text: str) -> tuple:
        try:
            return tuple(kind(v) for v in str(text).split(",") if v.strip() != "")
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected comma-separated numbers, got {text!r}") from None
    parse.__name__ = f"{kind.__name__}s"
    return parse


def _kind(f: dataclasses.Field) -> tuple[str, Any]:
    """``(kind, parser)`` of a field from its annotation string and default."""
    ann = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    parts = [p.strip() for p in re.split(r"\|", ann.replace("Optional[", "").rstrip("]"))]
    parts = [p for p in parts if p not in ("None", "NoneType")]
    base = parts[0] if parts else "str"
    default = f.default if f.default is not dataclasses.MISSING else None
    if f.name == "background":
        return "background", parse_background
    if base == "bool":
        return "bool", None
    if base.startswith("tuple") or isinstance(default, tuple):
        inner = float if "int" not in base else int
        return "tuple", _numbers(inner)
    if base == "int":
        return "int", int
    if base == "float":
        return "float", float
    if base in ("dict", "list") or base.startswith(("dict", "list")):
        return "json", json.loads
    return "str", str


def format_default(value: Any) -> str | None:
    """How a default reads in ``--help`` (``None`` = not shown)."""
    if value is None or value == "" or value == () or value == {}:
        return None
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, tuple):
        return ",".join(format_default(v) or "" for v in value)
    return str(value)


def _default_of(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    return None


def add_config(p: argparse.ArgumentParser | Any, cls: type, *, prefix: str = "",
               dest_prefix: str | None = None, shown: Any = None,
               skip: Iterable[str] = (), title: str | None = None) -> list[str]:
    """Add one flag per field of dataclass ``cls`` to parser (or group) ``p``.

    ``prefix``: flag and dest prefix (``"finetune."`` → ``--finetune.epochs``, dest
    ``finetune.epochs``); ``dest_prefix`` overrides the dest prefix alone (``"model."`` for
    ``ModelConfig`` fields shown as plain ``--grid-levels``). ``shown``: an instance whose
    values ``--help`` shows as the defaults (a preset); default: the dataclass defaults.
    ``skip``: fields without a flag. Returns the dests added.
    """
    dprefix = prefix if dest_prefix is None else dest_prefix
    docs = field_help(cls)
    target = p.add_argument_group(title) if title else p
    skip = set(skip)
    dests = []
    for f in dataclasses.fields(cls):
        if f.name in skip or not f.metadata.get("cli", True) or dataclasses.is_dataclass(
                _default_of(f)):
            continue
        kind, parse = _kind(f)
        default = getattr(shown, f.name) if shown is not None else _default_of(f)
        text = docs.get(f.name, "")
        shown_default = format_default(default)
        if shown_default is not None and kind != "json":
            text = f"{text} (default: {shown_default})" if text else f"default: {shown_default}"
        text = text.replace("%", "%%")
        dest = dprefix + f.name
        if f.metadata.get("positional"):
            target.add_argument(dest, metavar=f.name.upper(), nargs="?", default=None,
                                help=text)
            dests.append(dest)
            continue
        names = ["--" + prefix + f.name.replace("_", "-")]
        if "flag" in f.metadata:
            names.insert(0, "--" + prefix + f.metadata["flag"])
        kw: dict[str, Any] = {"dest": dest, "default": None, "help": text}
        if kind == "bool":
            kw["action"] = argparse.BooleanOptionalAction
        else:
            kw["type"] = parse
            if "choices" in f.metadata:
                kw["choices"] = list(f.metadata["choices"])
            kw["metavar"] = f.metadata.get("metavar") or {
                "int": "INT", "float": "FLOAT", "str": "TEXT", "tuple": "A,B,C",
                "background": "COLOUR", "json": "JSON"}[kind]
            if "choices" in kw:
                kw.pop("metavar")
        target.add_argument(*names, **kw)
        dests.append(dest)
    return dests


def given(args: argparse.Namespace, dests: Iterable[str], prefix: str = "") -> dict[str, Any]:
    """The values of ``dests`` (from :func:`add_config`) given on the command line, with
    ``prefix`` removed and nested by the remaining dots (``None`` = not given):
    ``{"epochs": 3, "model": {"net_width": 32}}``."""
    out: dict[str, Any] = {}
    for key in dests:
        value = getattr(args, key, None)
        if value is None or not key.startswith(prefix):
            continue
        parts = key[len(prefix):].split(".")
        node = out
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def apply(cfg: Any, values: dict[str, Any], where: str = "config") -> Any:
    """Set ``values`` (nested dicts for nested dataclasses) on dataclass ``cfg``; returns it.

    Unknown names raise :class:`ConfigError` naming ``where``; lists become tuples where the
    field's default is a tuple (JSON has no tuples)."""
    names = {f.name: f for f in dataclasses.fields(cfg)}
    for key, value in values.items():
        if key not in names:
            raise ConfigError(f"{where}: unknown option {key!r}; known: "
                              f"{', '.join(sorted(names))}")
        cur = getattr(cfg, key)
        if dataclasses.is_dataclass(cur) and isinstance(value, dict):
            apply(cur, value, f"{where}.{key}")
            continue
        if isinstance(value, list) and (isinstance(cur, tuple) or _kind(names[key])[0] in (
                "tuple", "background")):
            value = tuple(value)
        setattr(cfg, key, value)
    return cfg


def add_config_file(p: argparse.ArgumentParser) -> None:
    """Add ``--config FILE``: a JSON file of option values (e.g. a run's saved config.json),
    applied before the flags given on the command line."""
    p.add_argument("--config", dest="_config_file", metavar="FILE", default=None,
                   help="JSON file of options (a run's saved config.json); flags given on the "
                        "command line override it")


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


def config_to_json(cfg: Any) -> str:
    """A dataclass config as indented JSON (tuples as lists, paths as strings)."""
    return json.dumps(dataclasses.asdict(cfg), indent=2, default=str)
