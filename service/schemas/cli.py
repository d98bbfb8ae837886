"""CLI flags from the option declarations (:mod:`service.schemas.fields`,
the same as the models': no pydantic is loaded for ``--help``).

:func:`add_options` adds one ``--flag`` per declared option with its
description, default and accepted values as its help (``wandell batch
--help`` lists the same methods as ``/docs``). The values are not given to
argparse as ``choices``: the model checks them, so a bad value is the same
``error: invalid_parameter: ...`` (exit 2) on the command line as the 422
over HTTP.
"""

from __future__ import annotations

import types
import typing

from .fields import _UNSET


__all__ = ["add_options", "choices_help"]


def choices_help(choices) -> str:
    """How ``--help`` lists accepted values (also what the tests read back)."""
    return "one of: " + ", ".join(map(str, choices))


def _is_int(annotation) -> bool:
    args = typing.get_args(annotation) if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) \
        else (annotation,)
    return int in args


def add_options(parser, fields: dict, *, include=None, exclude=(), defaults=None, describe=None,
                choices=None) -> list[str]:
    """Add the CLI options (those with ``Opt.cli``) of ``fields`` (a group of
    :mod:`service.schemas.fields`) to ``parser``; returns their names.
    ``defaults``/``describe``/``choices``: another default, help text or
    list of accepted values per option for this command."""
    defaults, describe, choices = defaults or {}, describe or {}, choices or {}
    names = []
    for name, opt in fields.items():
        if not opt.cli or (include is not None and name not in include) or name in exclude:
            continue
        default = defaults.get(name, opt.given_default)
        text = describe.get(name, opt.description)
        accepted = choices.get(name, opt.choices)
        if accepted:
            text += f" ({choices_help(accepted)})"
        if default is not None:
            text += f"; default: {default}"
        if opt.type is bool:
            parser.add_argument("--" + name.replace("_", "-"), action="store_true",
                                help=describe.get(name, opt.description).replace("%", "%%"))
            names.append(name)
            continue
        kw = {"default": default, "help": text.replace("%", "%%")}
        if _is_int(opt.wire_type):
            kw["type"] = int
        if opt.metavar:
            kw["metavar"] = opt.metavar
        if opt.const is not _UNSET:
            kw.update(nargs="?", const=opt.const)
        parser.add_argument("--" + name.replace("_", "-"), **kw)
        names.append(name)
    return names
