"""The C configuration headers' pieces, shared by the pipeline's generators
(:mod:`iotnav.firmware.pipeline` for blocks 1-4, :mod:`iotnav.firmware.pipeline_blocks56` for
blocks 5 and 6): a configuration dataclass's fields as C members, their docstring lines, their
values as C literals, and one ``typedef struct`` with its ``*_CONFIG_DEFAULTS`` initialiser.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any


def c_fields(cls: type, methods: tuple[str, ...] | None = None) -> list[tuple[str, str]]:
    """``(name, kind)`` of the C members of ``cls``: kind ``int`` or ``real``, or ``method`` for
    a ``Literal`` of exactly ``methods`` (its index, an ``int32_t``)."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if tp is bool or tp is int:
            out.append((f.name, "int"))
        elif tp is float:
            out.append((f.name, "real"))
        elif (
            methods is not None and typing.get_origin(tp) is typing.Literal and typing.get_args(tp) == methods
        ):
            out.append((f.name, "method"))
        else:
            raise TypeError(f"{cls.__name__}.{f.name}: type {tp} has no C mapping")
    return out


def field_docs(cls: type) -> dict[str, str]:
    """First line of each attribute's description in a numpydoc ``Attributes`` section."""
    lines = (cls.__doc__ or "").splitlines()
    out: dict[str, str] = {}
    for i, ln in enumerate(lines):
        s = ln.strip()
        if " : " in s and i + 1 < len(lines):
            for name in s.split(" : ")[0].split(","):
                out[name.strip()] = lines[i + 1].strip().replace("*/", "* /")
    return out


def c_literal(v: Any, kind: str) -> str:
    """C text of the value ``v`` of a member of ``kind`` (``int``: decimal; ``real``:
    ``IOTNAV_R(repr)``); a non-finite real is refused (ValueError)."""
    if kind == "int":
        return str(int(v))
    if not math.isfinite(float(v)):
        raise ValueError(f"non-finite configuration value {v!r} cannot go into the C header")
    return f"IOTNAV_R({float(v)!r})"


def config_struct(prefix: str, cls: type, fields: list[tuple[str, str]], literals: list[str]) -> list[str]:
    """Header lines of ``<prefix>_config``, one member per field of ``cls`` (``int32_t`` for
    kinds ``int`` and ``method``, ``IOTNAV_REAL`` for ``real``, each with its docstring line),
    and its ``<PREFIX>_CONFIG_DEFAULTS`` initialiser of ``literals`` (C text, one per field)."""
    docs = field_docs(cls)
    out = ["", f"/* {cls.__module__}.{cls.__name__} (SI units, as the names say). */", "typedef struct {"]
    out += [
        f"    {'IOTNAV_REAL' if kind == 'real' else 'int32_t'} {name}; /* {docs.get(name, '')} */"
        for name, kind in fields
    ]
    out += [f"}} {prefix}_config;", "", f"/* The {cls.__name__} this header was generated with. */"]
    inits = [f"    {lit} /* {n} */" for (n, _), lit in zip(fields, literals, strict=True)]
    out += [
        f"#define {prefix.upper()}_CONFIG_DEFAULTS {{ \\",
        " \\\n".join(",\n".join(inits).split("\n")) + " \\",
        "}",
    ]
    return out
