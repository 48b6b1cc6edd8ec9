"""Command-line help read from the params schema, so that no option's meaning or default is
written a second time: a dataclass's documented fields (its docstring's ``Attributes:``) with
their defaults (conf/, through :func:`dexflow.params.conf_defaults`)."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
import typing

__all__ = ["add_schema_options", "field_docs", "options_from", "schema_help"]


def field_docs(cls: type) -> dict[str, str]:
    """``name -> description`` from the ``Attributes:`` section of ``cls``'s docstring."""
    doc = inspect.getdoc(cls) or ""
    _, _, section = doc.partition("Attributes:")
    docs: dict[str, str] = {}
    name = None
    for line in section.splitlines():
        found = re.match(r"^    (\w+): (.*)$", line)
        if found:
            name, docs[found.group(1)] = found.group(1), found.group(2).strip()
        elif name and line.startswith("        "):
            docs[name] += " " + line.strip()
        elif line.strip() and not line.startswith(" "):
            break
    return {name: _plain(text) for name, text in docs.items()}


def _plain(text: str) -> str:
    """Docstring markup as a terminal shows it: ``x`` and :func:`~a.b.x` as x."""
    text = re.sub(r":\w+:`~?([^`]*)`", lambda m: m.group(1).rpartition(".")[2], text)
    return re.sub(r"``([^`]*)``", r"\1", text)


def schema_help(cls: type, section: str) -> str:
    """One line per field of the dataclass ``cls``: ``section.field=default  description``."""
    docs = field_docs(cls)
    defaults = cls()
    lines = [f"fields of `{section}` (defaults from conf/{section}/):"]
    for f in dataclasses.fields(cls):
        value = getattr(defaults, f.name)
        lines.append(f"  {section}.{f.name}={value}  {docs.get(f.name, '')}".rstrip())
    return "\n".join(lines)


def _scalar_type(annotation) -> type:
    """``float`` of ``float | None``: the type a command-line string converts to."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    return args[0] if args else annotation


def add_schema_options(
    parser: argparse.ArgumentParser, cls: type, choices: dict[str, list[str]] | None = None
) -> None:
    """One ``--field-name`` option per field of the dataclass ``cls``, its help from the
    class's ``Attributes:`` and its default the class's (shown, not copied: an option not
    given is left to the class)."""
    docs, defaults, hints = field_docs(cls), cls(), typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        flag = "--" + f.name.replace("_", "-")
        default = getattr(defaults, f.name)
        text = docs.get(f.name, "")
        if hints[f.name] is bool:
            parser.add_argument(flag, action="store_true", default=None, help=text)
            continue
        shown = "" if default is None else f" (default: {default})"
        parser.add_argument(
            flag,
            type=_scalar_type(hints[f.name]),
            default=None,
            choices=(choices or {}).get(f.name),
            help=text + shown,
        )


def options_from(args: argparse.Namespace, cls: type):
    """An instance of ``cls`` from the options :func:`add_schema_options` added: the given
    ones, the class's defaults for the others."""
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls)}
    return cls(**{name: value for name, value in given.items() if value is not None})
