"""Command-line flags derived from frozen config dataclasses, declared nowhere else.

Every field of a config becomes one flag; a field that is itself a config dataclass becomes a
group of dotted flags (``--residual.steps``, ``--mppi.samples``). ``bool`` fields are
``--x``/``--no-x``; ``int``, ``float`` and ``str`` fields take a value; other types (tuples,
unions) stay at their preset's value. A preset is a named instance of the config (a module's
``PRESETS = {"tiny": Config(...), ...}``) and the flags given go on top of it:

    parser = argparse.ArgumentParser()
    add_flags(parser, DiagnoseConfig)
    cfg = from_flags(DiagnoseConfig, parser.parse_args(argv), base=PRESETS["default"])

This module imports no part of the library, so any module (a job's ``python -m`` entry point
included) may use it without importing the ``stride`` command.
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
import typing
from typing import Any, Callable, Mapping

_SCALARS = (int, float, str)
_SEP = "."


def _fields(cls) -> list[tuple[dataclasses.Field, Any]]:
    hints = typing.get_type_hints(cls)
    return [(f, hints[f.name]) for f in dataclasses.fields(cls)]


def _nested(kind) -> bool:
    return isinstance(kind, type) and dataclasses.is_dataclass(kind)


def _default(f: dataclasses.Field):
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def field_docs(cls) -> dict[str, str]:
    """Each field's description from the ``Attributes:`` section of ``cls``'s docstring
    (``name: text`` or ``a, b: text`` entries, continuation lines indented deeper)."""
    docs: dict[str, str] = {}
    lines = (cls.__doc__ or "").splitlines()
    if not any(line.strip() == "Attributes:" for line in lines):
        return docs
    start = next(i for i, line in enumerate(lines) if line.strip() == "Attributes:") + 1
    names: list[str] = []
    indent = None
    for line in lines[start:]:
        if not line.strip():
            break
        depth = len(line) - len(line.lstrip())
        head, sep, text = line.strip().partition(": ")
        if sep and (indent is None or depth <= indent) and all(
                n.strip().isidentifier() for n in head.split(",")):
            indent = depth
            names = [n.strip() for n in head.split(",")]
            for n in names:
                docs[n] = text.strip()
        elif names:
            for n in names:
                docs[n] += " " + line.strip()
    return docs


def flag_names(cls, prefix: str = "", defaults=None) -> dict[str, tuple[str, Any, Any]]:
    """``{dest: (flag, type, default)}`` for every field of ``cls`` a flag can set (nested
    configs recursively; ``dest`` is the dotted path with ``.`` as the separator). A nested
    field's default is the one its outer config holds (``defaults``: an instance of ``cls``),
    not its own class's."""
    out = {}
    for f, kind in _fields(cls):
        dest = prefix + f.name
        default = _default(f) if defaults is None else getattr(defaults, f.name)
        if _nested(kind):
            out.update(flag_names(kind, dest + _SEP, default))
        elif kind is bool or kind in _SCALARS:
            flag = "--" + _SEP.join(p.replace("_", "-") for p in dest.split(_SEP))
            out[dest] = (flag, kind, default)
    return out


def add_flags(parser: argparse.ArgumentParser, cls, skip: tuple[str, ...] = (),
              aliases: Mapping[str, str] | None = None,
              choices: Mapping[str, tuple] | None = None,
              required: tuple[str, ...] = ()) -> None:
    """One flag per settable field of ``cls`` (see :func:`flag_names`); unset flags stay
    ``None``. ``skip``: dotted field names the caller declares itself; ``aliases``: an older
    spelling a field's flag also answers to (``{"residual.steps": "--residual-steps"}``; a
    config class may declare its own in a ``FLAG_ALIASES`` class attribute);
    ``choices``: the values a field's flag accepts; ``required``: fields that must be given."""
    aliases = {**getattr(cls, "FLAG_ALIASES", {}), **(aliases or {})}
    choices = choices or {}
    for dest, (flag, kind, default) in flag_names(cls).items():
        if dest in skip:
            continue
        names = [flag, *([aliases[dest]] if dest in aliases else [])]
        help_ = _help(cls, dest) + (" (required)" if dest in required
                                    else f" (default {default!r})")
        if kind is bool:
            parser.add_argument(*names, dest=dest, action=argparse.BooleanOptionalAction,
                                default=None, help=help_.replace("%", "%%").strip())
        else:
            parser.add_argument(*names, dest=dest, type=kind, default=None,
                                choices=choices.get(dest), required=dest in required,
                                help=help_.replace("%", "%%").strip())


def _help(cls, dest: str) -> str:
    """The docstring description of the field at dotted ``dest`` (empty if none)."""
    *path, name = dest.split(_SEP)
    for part in path:
        cls = typing.get_type_hints(cls)[part]
    return field_docs(cls).get(name, "")


def replace(cfg, values: Mapping[str, Any]):
    """``cfg`` with dotted ``values`` (``{"residual.steps": 10}``) set; ``None`` values are
    skipped."""
    top: dict[str, Any] = {}
    inner: dict[str, dict[str, Any]] = {}
    for dest, v in values.items():
        if v is None:
            continue
        head, _, rest = dest.partition(_SEP)
        if rest:
            inner.setdefault(head, {})[rest] = v
        else:
            top[head] = v
    for head, sub in inner.items():
        top[head] = replace(getattr(cfg, head), sub)
    return dataclasses.replace(cfg, **top) if top else cfg


def from_flags(cls, args: argparse.Namespace, base=None):
    """``base`` (an instance of ``cls``, or None for the defaults) with the flags that were
    given on top."""
    return replace(cls() if base is None else base,
                   {dest: getattr(args, dest, None) for dest in flag_names(cls)})


def preset(cls, presets: Mapping[str, Any], name: str):
    """The named preset, an instance of ``cls`` (``SystemExit`` for an unknown name)."""
    if name not in presets:
        raise SystemExit(f"unknown preset {name!r}; choose from {', '.join(presets)}")
    p = presets[name]
    if not isinstance(p, cls):
        raise TypeError(f"preset {name!r} is a {type(p).__name__}, not a {cls.__name__}: "
                        f"presets are named instances of their config")
    return p


def to_flags(cfg, prefix: str = "") -> list[str]:
    """Every settable field of ``cfg`` as flags: parsed on top of the defaults they rebuild
    ``cfg`` (the inverse of :func:`from_flags`)."""
    flags = []
    for dest, (flag, kind, _) in flag_names(type(cfg)).items():
        value = cfg
        for part in dest.split(_SEP):
            value = getattr(value, part)
        if kind is bool:
            flags.append(flag if value else "--no-" + flag[2:])
        else:
            flags += [flag, str(value)]
    return flags


def config_main(prog: str, cls, presets: Mapping[str, Any], run: Callable,
                argv: list[str] | None = None, description: str = "") -> None:
    """A module's own command line (``python -m ...``, ``experiments/*.py``): ``--preset`` and
    the flags of ``cls``, then ``run(cfg, command, log=print)``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("--preset", default="default", help=f"one of {', '.join(presets)}")
    add_flags(parser, cls)
    args = parser.parse_args(argv)
    cfg = from_flags(cls, args, preset(cls, presets, args.preset))
    run(cfg, shlex.join([*prog.split(), *argv]), log=lambda line: print(line, flush=True))
