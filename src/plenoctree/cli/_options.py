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
- field metadata (``field(metadata={...})``), or a command's ``fields={name: {...}}``, may
  add ``"choices"``, ``"flag"`` (the flag's name instead of the field's, e.g. ``"steps"``;
  one flag per field, never two), ``"positional": True``, ``"cli": False`` (no flag),
  ``"metavar"``; a ``show_progress`` field is ``--progress/--no-progress``.

Every parser is a :class:`Parser`: abbreviated flags are refused, and an unknown flag is
reported by its sub-command, naming it and the closest known flag.

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

from .._config import (apply, field_help, flag_name, load_config_file, parse_background,
                       spell_flags)
from ..errors import ConfigError

__all__ = ["add_command", "add_config", "given", "layered", "apply", "field_help",
           "load_config_file", "parse_background", "add_config_file", "format_default",
           "Parser", "CommandParser", "hidden_sections"]


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


def _add_field(target: Any, f: dataclasses.Field, spec: dict[str, Any], prefix: str,
               dest: str, default: Any) -> None:
    """Add the flag (or positional argument) of one config field (see :func:`add_config`)."""
    kind, parse = _kind(f)
    text = field_help_text(spec.get("help", ""), default, kind)
    if spec.get("positional"):
        target.add_argument(dest, metavar=f.name.upper(), help=text)
        return
    names = [flag_name(f, prefix, spec.get("flag"))]
    if spec.get("short") and not prefix:
        names.append(spec["short"])
    kw: dict[str, Any] = {"dest": dest, "default": None, "help": text}
    if spec.get("required") and not prefix:
        kw["required"] = True
    metavar = spec.get("metavar") or {"background": "COLOUR", "json": "JSON",
                                      "tuple": "X"}.get(kind, f.name.upper())
    if kind == "bool":
        kw["action"] = argparse.BooleanOptionalAction
    elif kind == "tuple":
        ann = f.type if isinstance(f.type, str) else str(f.type)
        kw.update(nargs="+", action=_numbers(parse, _tuple_length(ann)), metavar=metavar)
    elif "choices" in spec:
        kw.update(type=parse, choices=list(spec["choices"]))
    else:
        kw.update(type=parse, metavar=metavar)
    target.add_argument(*names, **kw)


def field_help_text(text: str, default: Any, kind: str) -> str:
    """``--help`` of a field: its docstring and the real default (``(default: 0.01)``)."""
    shown_default = format_default(default)
    if shown_default is not None and kind != "json":
        text = f"{text} (default: {shown_default})" if text else f"default: {shown_default}"
    return text.replace("``", "").replace("%", "%%")


def add_config(p: argparse.ArgumentParser | Any, cls: type, *, prefix: str = "",
               dest_prefix: str | None = None, shown: Any = None, skip: Iterable[str] = (),
               fields: dict[str, dict[str, Any]] | None = None,
               nested: dict[str, dict[str, Any]] | None = None) -> list[str]:
    """Add one flag per field of dataclass ``cls`` to parser (or group) ``p``.

    ``prefix``: flag and dest prefix (``"finetune."`` → ``--finetune.epochs``, dest
    ``finetune.epochs``); ``dest_prefix`` overrides the dest prefix alone (``"model."`` for
    ``ModelConfig`` fields shown as plain ``--grid-levels``). ``shown``: an instance whose
    values ``--help`` shows as the defaults (a preset); default: the dataclass defaults.
    ``skip``: fields without a flag. ``fields``: per-field flag options over the field's
    metadata, ``{name: {...}}`` with ``"positional": True`` (a required positional
    argument), ``"required": True`` (a flag that must be given), ``"short"`` (an extra short
    flag, ``"-o"``), ``"flag"`` (the flag's name when it is not the field's), ``"choices"``,
    ``"metavar"``, ``"help"``. ``nested``: fields holding a dataclass whose own fields get
    flags too, ``{field: add_config keyword arguments}`` (flags unprefixed unless given a
    ``prefix``; dest ``<field>.<name>``). Returns the dests added.
    """
    dprefix = prefix if dest_prefix is None else dest_prefix
    docs, fields, nested, skip = field_help(cls), fields or {}, nested or {}, set(skip)
    dests: list[str] = []
    later: list[tuple[type, dict[str, Any]]] = []
    for f in dataclasses.fields(cls):
        value = getattr(shown, f.name) if shown is not None else _default_of(f)
        if f.name in nested:
            later.append((type(value), {"prefix": prefix, "dest_prefix": f"{dprefix}{f.name}.",
                                        "shown": value, **nested[f.name]}))
            continue
        if f.name in skip or not f.metadata.get("cli", True) or dataclasses.is_dataclass(value):
            continue
        spec = {"help": docs.get(f.name, ""), **f.metadata, **fields.get(f.name, {})}
        _add_field(p, f, spec, prefix, dprefix + f.name, value)
        dests.append(dprefix + f.name)
    for inner_cls, kw in later:
        dests += add_config(p, inner_cls, **kw)
    return dests


def layered(args: argparse.Namespace, base: Any, where: str,
            layer: Callable[[Any, dict, str], Any] = apply) -> Any:
    """``base`` (a config instance: defaults or a preset) with ``--config FILE`` and then the
    flags of ``args._dests`` set by ``layer`` (default :func:`apply`): the one layering rule of
    every command."""
    file = getattr(args, "_config_file", None)
    layer(base, load_config_file(file), str(file or where))
    return layer(base, given(args, args._dests), where)


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


class Parser(argparse.ArgumentParser):
    """The parser of ``plenoctree`` and of every sub-command: no abbreviated flags, and an
    unknown flag is reported by the sub-command that got it, with its usage and the closest
    flag it knows (``--finetune-epochs`` → did you mean ``--finetune.epochs``?)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs["allow_abbrev"] = False
        super().__init__(*args, **kwargs)

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        ns, extras = super().parse_known_args(args, namespace)
        if extras and getattr(self, "_is_command", False):
            self.error(self.unknown(extras))
        return ns, extras

    def unknown(self, extras: list[str]) -> str:
        """The error for the unknown arguments ``extras``, naming each."""
        import difflib

        hints = []
        for word in extras:
            close = difflib.get_close_matches(word.split("=")[0], list(self._option_string_actions),
                                              n=1, cutoff=0.75) if word.startswith("-") else []
            hints.append(f"{word} (did you mean {close[0]}?)" if close else word)
        return "unrecognized arguments: " + " ".join(hints)


class CommandParser(Parser):
    """A sub-command's parser (see :class:`Parser`)."""

    _is_command = True


class _HelpSections(argparse.Action):
    """``--help-all`` / ``--help-stage NAME``: ``--help`` with the hidden option sections
    (all, or the one named) shown."""

    def __init__(self, option_strings, dest, sections: dict[str, Any], **kw):
        super().__init__(option_strings, dest, **kw)
        self.sections = sections

    def __call__(self, parser, namespace, values, option_string=None):
        for name, group in self.sections.items():
            if not values or values == name:
                for action in group._group_actions:
                    action.help = getattr(action, "_hidden_help", action.help)
        parser.print_help()
        parser.exit()


def hidden_sections(p: argparse.ArgumentParser, sections: dict[str, Any]) -> None:
    """Hide the options of the argument groups ``sections`` (``{name: group}``) from
    ``--help``; add ``--help-all`` and ``--help-stage NAME``, which show them."""
    for group in sections.values():
        for action in group._group_actions:
            action._hidden_help, action.help = action.help, argparse.SUPPRESS  # type: ignore
    names = ", ".join(sections)
    p.add_argument("--help-all", nargs=0, action=_HelpSections, sections=sections,
                   help="show every option, the stages' too, and exit")
    p.add_argument("--help-stage", choices=list(sections), action=_HelpSections,
                   sections=sections, metavar="STAGE",
                   help=f"show the options of one stage ({names}) and exit")


def add_command(sub: argparse._SubParsersAction, name: str, cls: type,
                run: Callable[[Any, argparse.Namespace], int | None], *, help: str,
                description: str | None = None, base: Callable[[], Any] | None = None,
                **options: Any) -> argparse.ArgumentParser:
    """Add the sub-command ``name`` whose options are the fields of dataclass ``cls``:
    ``--config FILE``, ``--quiet`` (and ``--progress`` when ``cls`` has ``show_progress``)
    and one flag per field (:func:`add_config`; ``options`` are its keyword arguments, and
    ``positional``: the fields taken as positional arguments). When used, it calls
    ``run(cfg, args)`` with ``cfg`` = ``base()`` (default ``cls()``) under ``--config`` and
    the flags given (:func:`layered`; ``--quiet`` turns progress bars off unless
    ``--progress`` is given); ``args`` holds the flags that are not options (``--json``,
    ``--quiet``); ``args._resolve(args)`` gives the config alone (tests). Returns the parser,
    to add those flags."""
    from ._output import add_quiet, quiet_progress

    p = sub.add_parser(name, help=help, description=description)
    add_config_file(p)
    add_quiet(p)
    positional = {n: {"positional": True} for n in options.pop("positional", ())}
    fields = {**options.pop("fields", {}), **positional}
    dests = add_config(p, cls, fields=fields, **options)
    make = base or cls

    def resolve(args: argparse.Namespace) -> Any:
        return quiet_progress(layered(args, make(), name), args)

    p.set_defaults(func=lambda args: _spelled(p, lambda: run(resolve(args), args)),
                   _dests=dests, _resolve=resolve)
    return p


def _spelled(p: argparse.ArgumentParser, call: Callable[[], Any]) -> Any:
    """``call()``, its ConfigError spelling the config's field names as ``p``'s flags
    (``finetune: lr_decay must`` → ``--lr-decay must``) and a config key checked by
    :func:`apply` with the flag the command gives it (compress's ``'views' (--views) must``
    → ``'views' (--orbit-views) must``, lod's ``'lod.max_depth' must`` → ``'lod.max_depth'
    (--max-depth) must``)."""
    try:
        return call()
    except ConfigError as e:
        actions = [a for a in p._actions if a.option_strings and a.dest != "help"]
        by_dest = {a.dest: a.option_strings[0] for a in actions}

        def key_flag(m: re.Match) -> str:
            flag = by_dest.get(m.group(1), m.group(2))
            return f"'{m.group(1)}'" + (f" ({flag})" if flag else "")

        keyed = re.sub(r"'([\w.]+)'(?: \((--[\w.-]+)\))?(?= must)", key_flag, str(e))
        spelled = spell_flags(keyed, {a.dest.rsplit(".", 1)[-1]: a.option_strings[0]
                                      for a in actions})
        if spelled == str(e):
            raise
        raise ConfigError(spelled) from e
