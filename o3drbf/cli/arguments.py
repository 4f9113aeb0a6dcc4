"""argparse arguments generated from the options' tables (:mod:`o3drbf.options.flags`).

:func:`add_options` adds an entry point's options to a (sub)parser, with
the defaults of :func:`o3drbf.options.defaults` and the help of
:data:`o3drbf.options.flags.FLAGS`; :func:`options_from_args` turns the
parsed values back into the entry point's options object.  The value
parsers of :mod:`o3drbf.options.values` raise ValueError; :func:`value_type`
turns that into argparse's usage error (one line, exit status 2).
"""

from __future__ import annotations

import argparse
import functools

from o3drbf.options import defaults, values
from o3drbf.options.flags import ENTRY_FLAGS, GROUPS, flag_for, help_text, help_values

__all__ = ["add_options", "options_from_args", "option_names", "value_type", "positive_int", "non_negative_int", "validated"]


def value_type(parse, name: str | None = None, **kw):
    """An argparse ``type=`` from a parser that raises ValueError: its one-line message becomes the usage error."""

    @functools.wraps(parse)
    def convert(text):
        try:
            return parse(text, **kw)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    convert.__name__ = name or parse.__name__
    return convert


positive_int = value_type(values.whole_number, "positive_int", low=1)
non_negative_int = value_type(values.whole_number, "non_negative_int", low=0)
count_or_auto = value_type(values.count_or_auto)


def _argument(entry: str, name: str, default, help_: str, constants: dict) -> tuple[tuple, dict]:
    flag = flag_for(entry, name)
    names = flag.flags or ("--" + name.replace("_", "-"),)
    kw: dict = {"dest": name, "default": default, "help": help_}
    kind = flag.kind
    if kind == "float":
        kw["type"] = float
    elif kind == "int":
        kw["type"] = value_type(values.whole_number, "whole_number", low=flag.low)
    elif kind == "count":
        kw["type"] = count_or_auto
    elif kind == "auto_bool":
        kw["type"] = value_type(values.auto_or_bool)
    elif kind == "box":
        kw["type"] = value_type(values.box_or_rule)
    elif kind == "rgb":
        kw["type"] = value_type(values.rgb)
        kw["default"] = list(default)
    elif kind == "size":
        kw.update(type=positive_int, nargs=2, default=tuple(default))
    elif kind == "bool":
        kw["action"] = argparse.BooleanOptionalAction
    elif kind in ("store_true", "store_false"):
        kw["action"] = kind
    elif kind == "choice":
        kw["choices"] = list(constants[flag.choices])
    elif kind == "layers":
        kw.update(nargs="+", choices=list(constants["layers"].split(", ")), default=list(default))
    if flag.metavar is not None:
        kw["metavar"] = flag.metavar
    return names, kw


def add_options(parser: argparse.ArgumentParser, entry: str = "reconstruct") -> dict:
    """Add ``entry``'s options (:data:`o3drbf.options.flags.ENTRY_FLAGS`) to ``parser``; returns the argument groups by key.

    Every flag's default is the entry point's (:func:`o3drbf.options.defaults`, read now) and its help
    the table's text with the default clause written from it.
    """
    table = defaults(entry)
    constants = help_values()
    groups = {}
    for key, names in ENTRY_FLAGS[entry]:
        group = groups[key] = parser.add_argument_group(GROUPS[key])
        for name in names:
            default = table[name]
            names_, kw = _argument(entry, name, default, help_text(entry, name, default, constants), constants)
            group.add_argument(*names_, **kw)
    return groups


def option_names(entry: str) -> list[str]:
    """The options ``entry`` offers on the command line (its flat names), in ``--help`` order."""
    return [name for _, names in ENTRY_FLAGS[entry] for name in names]


def options_from_args(args: argparse.Namespace, entry: str = "reconstruct"):
    """The options object of ``entry`` from arguments added by :func:`add_options`, not yet validated.

    ``reconstruct``: :class:`~o3drbf.options.Options`; ``photos``: :class:`~o3drbf.options.PhotoOptions`;
    ``compare``: :class:`~o3drbf.options.CompareOptions`; ``view``: :class:`~o3drbf.options.ViewOptions`.
    ``--all-points`` (where offered) is ``surface_count=None``.
    """
    from o3drbf.options import CompareOptions, Options, PhotoOptions, ViewOptions

    cls = {"reconstruct": Options, "photos": PhotoOptions, "compare": CompareOptions, "view": ViewOptions}[entry]
    flat = {name: getattr(args, name) for name in option_names(entry) if hasattr(args, name)}
    for name in ("background", "hide", "window_size"):
        if name in flat and isinstance(flat[name], list):
            flat[name] = tuple(flat[name])
    if entry == "photos" and flat.get("photo_consistency") == 0:
        flat["photo_consistency"] = None  # 0: the visual hull
    if getattr(args, "all_points", False):
        flat["surface_count"] = None
    return cls.create(**flat)


def validated(options, entry: str):
    """``options.validate()``, its one-line refusal naming the command-line flag (``--poisson-depth``, not ``poisson_depth``)."""
    import re

    try:
        return options.validate()
    except ValueError as exc:
        text = str(exc)
        for name in sorted(option_names(entry), key=len, reverse=True):
            flag = flag_for(entry, name)
            dashed = (flag.flags or ("--" + name.replace("_", "-"),))[0]
            pattern = rf"(?<![-\w]){name}(?![-\w])" if "_" in name else rf"^{name}(?![-\w])"
            text = re.sub(pattern, dashed, text)
        raise ValueError(text) from None
