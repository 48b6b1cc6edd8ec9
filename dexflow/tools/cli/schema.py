"""Command-line help read from the params schema, so that no option's meaning or default is
written a second time: a dataclass's documented fields (its docstring's ``Attributes:``) with
their defaults (conf/, through :func:`dexflow.params.conf_defaults`)."""

from __future__ import annotations

import dataclasses
import inspect
import re

__all__ = ["field_docs", "schema_help"]


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
    return docs


def schema_help(cls: type, section: str) -> str:
    """One line per field of the dataclass ``cls``: ``section.field=default  description``."""
    docs = field_docs(cls)
    defaults = cls()
    lines = [f"fields of `{section}` (defaults from conf/{section}/):"]
    for f in dataclasses.fields(cls):
        value = getattr(defaults, f.name)
        lines.append(f"  {section}.{f.name}={value}  {docs.get(f.name, '')}".rstrip())
    return "\n".join(lines)
