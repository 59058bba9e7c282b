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
  allowed); tuples of numbers → ``--x 1 2 3`` or ``--x 1,2,3`` (a length fixed by the
  annotation, ``tuple[float, float]``, is checked); ``dict``/``list`` → a JSON value; a field
  named ``background`` → ``white``, ``black`` or ``R,G,B`` (parsed with the other values by
  :func:`apply`, so a config file may use the same names);
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
from typing import Any, Callable, Iterable

from .._config import apply, field_help, load_config_file, parse_background
from ..errors import ConfigError

__all__ = ["add_command", "add_config", "given", "layered", "apply", "field_help",
           "load_config_file", "parse_background", "add_config_file", "config_to_json",
           "format_default"]


def _numbers(conv: type, length: int | None):
    """The argparse action of a tuple field: ``--x 1 2 3`` or ``--x 1,2,3`` -> a list of
    numbers (``length`` of them when the annotation fixes it, e.g. ``tuple[float, float]``)."""

    class Numbers(argparse.Action):
        def __call__(self, parser, namespace, values, option_string=None):
            try:
                nums = [conv(v) for text in values for v in str(text).split(",") if v.strip()]
            except ValueError:
                parser.error(f"{option_string}: expected numbers, got {' '.join(values)!r}")
            if length is not None and len(nums) != length:
                parser.error(f"{option_string}: expected {length} numbers, got "
                             f"{' '.join(values)!r}")
            setattr(namespace, self.dest, nums)

    return Numbers


def _tuple_length(ann: str) -> int | None:
    """``tuple[float, float]`` -> 2; ``tuple`` / ``tuple[float, ...]`` -> None."""
    m = re.search(r"tuple\[([^\]]*)\]", ann)
    if not m or "..." in m.group(1):
        return None
    return len([t for t in m.group(1).split(",") if t.strip()])


def _kind(f: dataclasses.Field) -> tuple[str, Any]:
    """``(kind, parser)`` of a field from its annotation string and default."""
    ann = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    parts = [p.strip() for p in re.split(r"\|", ann.replace("Optional[", "").rstrip("]"))]
    parts = [p for p in parts if p not in ("None", "NoneType")]
    base = parts[0] if parts else "str"
    default = f.default if f.default is not dataclasses.MISSING else None
    if f.name == "background":
        return "background", str          # parsed by _config.apply (flags and config files)
    if base == "bool":
        return "bool", None
    if base.startswith("tuple") or isinstance(default, tuple):
        return "tuple", (int if "int" in base and "float" not in base else float)
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
               skip: Iterable[str] = (), title: str | None = None,
               positional: Iterable[str] = (), short: dict[str, str] | None = None,
               rename: dict[str, str] | None = None,
               aliases: dict[str, str] | None = None,
               choices: dict[str, Iterable[str]] | None = None,
               required: Iterable[str] = (),
               metavars: dict[str, str] | None = None,
               nested: dict[str, dict[str, Any]] | None = None) -> list[str]:
    """Add one flag per field of dataclass ``cls`` to parser (or group) ``p``.

    ``prefix``: flag and dest prefix (``"finetune."`` → ``--finetune.epochs``, dest
    ``finetune.epochs``); ``dest_prefix`` overrides the dest prefix alone (``"model."`` for
    ``ModelConfig`` fields shown as plain ``--grid-levels``). ``shown``: an instance whose
    values ``--help`` shows as the defaults (a preset); default: the dataclass defaults.
    ``skip``: fields without a flag. ``positional``: fields taken as positional arguments
    (required). ``short``: extra short flags (``{"out": "-o"}``). ``rename``: flag names
    differing from the field's (``{"show_progress": "progress"}``). ``aliases``: an older
    flag name kept working (``{"limit": "--limit"}``). ``choices``: allowed values of
    fields (as the ``"choices"`` metadata). ``required``: flags that must be given on the
    command line (e.g. ``--out``). ``metavars``: shown value names (``{"tree": "JSON"}``).
    ``nested``: fields holding a dataclass whose own fields get
    flags too, ``{field: add_config keyword arguments}`` (flags unprefixed unless given a
    ``prefix``; dest ``<field>.<name>``). Returns the dests added.
    """
    choices, required, metavars = choices or {}, set(required), metavars or {}
    positional, short, rename, aliases = set(positional), short or {}, rename or {}, aliases or {}
    dprefix = prefix if dest_prefix is None else dest_prefix
    docs = field_help(cls)
    target = p.add_argument_group(title) if title else p
    skip = set(skip)
    dests: list[str] = []
    later: list[tuple[type, dict[str, Any]]] = []
    nested = nested or {}
    for f in dataclasses.fields(cls):
        if f.name in nested:
            inner = getattr(shown, f.name) if shown is not None else _default_of(f)
            kw = {"prefix": prefix, "dest_prefix": f"{dprefix}{f.name}.", "shown": inner,
                  **nested[f.name]}
            later.append((type(inner), kw))
            continue
        if f.name in skip or not f.metadata.get("cli", True) or dataclasses.is_dataclass(
                _default_of(f)):
            continue
        kind, parse = _kind(f)
        default = getattr(shown, f.name) if shown is not None else _default_of(f)
        text = docs.get(f.name, "")
        shown_default = format_default(default)
        if shown_default is not None and kind != "json":
            text = f"{text} (default: {shown_default})" if text else f"default: {shown_default}"
        text = text.replace("``", "").replace("%", "%%")
        dest = dprefix + f.name
        if f.metadata.get("positional") or f.name in positional:
            target.add_argument(dest, metavar=f.name.upper(), help=text)
            dests.append(dest)
            continue
        names = ["--" + prefix + rename.get(f.name, f.name).replace("_", "-")]
        if "flag" in f.metadata:
            names.insert(0, "--" + prefix + f.metadata["flag"])
        if f.name in short and not prefix:
            names.append(short[f.name])
        if f.name in aliases and not prefix:
            names.append(aliases[f.name])
        kw: dict[str, Any] = {"dest": dest, "default": None, "help": text}
        if f.name in required and not prefix:
            kw["required"] = True
        if kind == "bool":
            kw["action"] = argparse.BooleanOptionalAction
        elif kind == "tuple":
            ann = f.type if isinstance(f.type, str) else str(f.type)
            kw["nargs"] = "+"
            kw["action"] = _numbers(parse, _tuple_length(ann))
            kw["metavar"] = metavars.get(f.name) or f.metadata.get("metavar") or "X"
        else:
            kw["type"] = parse
            if "choices" in f.metadata or f.name in choices:
                kw["choices"] = list(choices.get(f.name) or f.metadata["choices"])
            kw["metavar"] = metavars.get(f.name) or f.metadata.get("metavar") or {
                "background": "COLOUR", "json": "JSON"}.get(kind, f.name.upper())
            if "choices" in kw:
                kw.pop("metavar")
        target.add_argument(*names, **kw)
        dests.append(dest)
    for inner_cls, kw in later:
        dests += add_config(p, inner_cls, **kw)
    return dests


def layered(args: argparse.Namespace, base: Any, where: str) -> Any:
    """``base`` (a config instance: defaults or a preset) with ``--config FILE`` and then the
    flags of ``args._dests`` applied: the one layering rule of every command."""
    apply(base, load_config_file(getattr(args, "_config_file", None)),
          where=str(getattr(args, "_config_file", None) or where))
    return apply(base, given(args, args._dests), where=where)


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


def add_config_file(p: argparse.ArgumentParser) -> None:
    """Add ``--config FILE``: a JSON file of option values (e.g. a run's saved config.json),
    applied before the flags given on the command line."""
    p.add_argument("--config", dest="_config_file", metavar="FILE", default=None,
                   help="JSON file of options (a run's saved config.json); flags given on the "
                        "command line override it")


def config_to_json(cfg: Any) -> str:
    """A dataclass config as indented JSON (tuples as lists, paths as strings)."""
    return json.dumps(dataclasses.asdict(cfg), indent=2, default=str)


def add_command(sub: argparse._SubParsersAction, name: str, cls: type,
                run: Callable[[Any, argparse.Namespace], int | None], *, help: str,
                description: str | None = None, base: Callable[[], Any] | None = None,
                **options: Any) -> argparse.ArgumentParser:
    """Add the sub-command ``name`` whose options are the fields of dataclass ``cls``:
    ``--config FILE`` and one flag per field (:func:`add_config`; ``options`` are its keyword
    arguments). When used, it calls ``run(cfg, args)`` with ``cfg`` = ``base()`` (default
    ``cls()``) under ``--config`` and the flags given (:func:`layered`); ``args`` holds the
    flags that are not options (``--json``, ``--quiet``); ``args._resolve(args)`` gives the
    config alone (tests). Returns the parser, to add those flags."""
    p = sub.add_parser(name, help=help, description=description)
    add_config_file(p)
    dests = add_config(p, cls, **options)
    make = base or cls

    def resolve(args: argparse.Namespace) -> Any:
        return layered(args, make(), name)

    p.set_defaults(func=lambda args: run(resolve(args), args), _dests=dests, _resolve=resolve)
    return p
