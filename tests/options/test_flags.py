"""The flags of every command are generated from the options' tables: their defaults are the entry point's
(:func:`o3drbf.options.defaults`), their help the help table's text (:data:`o3drbf.options.flags.FLAGS`) with
the default clause written from that default, so neither can drift from the code."""

from __future__ import annotations

import pytest

from o3drbf.cli.arguments import option_names
from o3drbf.cli.commands import build_parser
from o3drbf.options import COMPARE_OVERRIDES, MAX_RESOLUTION, PHOTO_OVERRIDES, VIEW_DEFAULTS, defaults
from o3drbf.options.flags import ENTRY_FLAGS, flag_for, help_text, help_values
from o3drbf.solvers import DENSE_AUTO_MAX

ENTRIES = ("reconstruct", "photos", "compare", "view")


def command(name: str):
    return next(a for a in build_parser()._actions if a.dest == "command").choices[name]


def action(parser, dest: str):
    return next(a for a in parser._actions if a.dest == dest)


def _same(value):
    return tuple(value) if isinstance(value, list) else value


@pytest.mark.parametrize("entry", ENTRIES)
def test_every_flag_is_the_table(entry):
    """Each option the command offers: the table's default, the table's help (text and default clause), its flag string."""
    parser, table, values = command(entry), defaults(entry), help_values()
    for name in option_names(entry):
        a = action(parser, name)
        flag = flag_for(entry, name)
        assert a.option_strings[0] == (flag.flags or ("--" + name.replace("_", "-"),))[0], name
        assert a.help == help_text(entry, name, table[name], values), name
        assert flag.help.format(**values).replace("%", "%%") in a.help, name
        default = table[name]
        if flag.kind not in ("store_false",):
            assert _same(a.default) == _same(default), (name, a.default, default)
        else:
            assert a.default is True and default is True, name
    # and nothing offered that the table does not hold
    assert set(option_names(entry)) <= set(table)


def test_each_entry_points_defaults_reach_its_help(monkeypatch):
    """A changed default of the table (an entry point's override) is what ``--help`` says, without editing a help text."""
    monkeypatch.setitem(PHOTO_OVERRIDES, "delta", 5.5)
    monkeypatch.setitem(COMPARE_OVERRIDES, "surface_count", 2500)
    monkeypatch.setitem(VIEW_DEFAULTS, "zoom", 0.75)
    assert "multiorder: first-order weight (default 5.5)" in " ".join(command("photos").format_help().split())
    assert action(command("compare"), "surface_count").default == 2500
    view = command("view")
    assert action(view, "zoom").default == 0.75 and "(default 0.75)" in " ".join(view.format_help().split())


def test_help_states_the_code_constants():
    """The --solver switch is the solver's DENSE_AUTO_MAX; the viewer's and the carving's limits are MAX_RESOLUTION."""
    assert f"dense up to {DENSE_AUTO_MAX:,} constraints" in action(command("reconstruct"), "solver").help
    assert f"dense up to {DENSE_AUTO_MAX:,} constraints" in action(command("compare"), "solver").help
    assert f"2..{MAX_RESOLUTION}" in action(command("view"), "resolution").help
    assert f"8..{MAX_RESOLUTION}" in action(command("photos"), "voxels").help


def test_every_option_has_a_flag_entry():
    for entry, groups in ENTRY_FLAGS.items():
        for _, names in groups:
            for name in names:
                assert flag_for(entry, name).help, (entry, name)
