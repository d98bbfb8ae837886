"""CLI flags from the option models (:mod:`service.schemas.options`).

:func:`add_options` adds one ``--flag`` per model field with the field's
description, default and accepted values as its help (``wandell batch
--help`` lists the same methods as ``/docs``). The values are not given to
argparse as ``choices``: the model checks them, so a bad value is the same
``error: invalid_parameter: ...`` (exit 2) on the command line as the 422
over HTTP.
"""

from __future__ import annotations

import types
import typing

from .options import _UNSET, option_fields

__all__ = ["add_options", "choices_help"]


def choices_help(choices) -> str:
    """How ``--help`` lists accepted values (also what the tests read back)."""
    return "one of: " + ", ".join(map(str, choices))


def _is_int(annotation) -> bool:
    args = typing.get_args(annotation) if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) \
        else (annotation,)
    return int in args


def add_options(parser, model, *, include=None, exclude=(), defaults=None, describe=None) -> list[str]:
    """Add ``model``'s CLI fields (those with ``Opt.cli``) to ``parser``;
    returns their names. ``defaults``/``describe``: another default or help
    text per field for this command."""
    defaults, describe = defaults or {}, describe or {}
    names = []
    for name, (f, opt) in option_fields(model).items():
        if not opt.cli or (include is not None and name not in include) or name in exclude:
            continue
        default = defaults.get(name, f.default if opt.wire_default is _UNSET else opt.wire_default)
        text = describe.get(name, f.description)
        if opt.choices:
            text += f" ({choices_help(opt.choices)})"
        if default is not None:
            text += f"; default: {default}"
        kw = {"default": default, "help": text.replace("%", "%%")}
        if _is_int(opt.wire if opt.wire is not None else f.annotation):
            kw["type"] = int
        if opt.metavar:
            kw["metavar"] = opt.metavar
        parser.add_argument("--" + name.replace("_", "-"), **kw)
        names.append(name)
    return names
