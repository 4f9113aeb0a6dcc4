"""Help texts and documented defaults come from the code's tables, so they cannot drift from it.

``o3drbf reconstruct --help``, the viewer's ``--help`` and the defaults of
the public functions are checked against :data:`o3drbf.DEFAULTS` and the
constants they describe (``o3drbf.options``, ``o3drbf.solvers``).
"""

from __future__ import annotations

import inspect
import re

import pytest

import o3drbf
from o3drbf.cli.commands import build_parser
from o3drbf.options import (API_ONLY, AUTO_SIZES, DEFAULTS, DENOISE_MIN_NOISE, MAX_RESOLUTION, PAPER_VALUES, TILE_DEFAULTS, ExtractOptions,
                            Options)
from o3drbf.solvers import DENSE_AUTO_MAX

NUMBER = re.compile(r"(?<![\w.])\d[\d,]*(?:\.\d+)?(?![\w.])")


def command(name: str):
    parser = build_parser()
    return next(a for a in parser._actions if a.dest == "command").choices[name]


def option(parser, flag: str):
    return next(a for a in parser._actions if flag in a.option_strings)


def table_values() -> set[float]:
    """Every number the tables hold (and MAX_RESOLUTION, DENSE_AUTO_MAX, DENOISE_MIN_NOISE)."""
    values = set()
    for table in (DEFAULTS, AUTO_SIZES, PAPER_VALUES, TILE_DEFAULTS):
        values |= {float(v) for v in table.values() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    return values | {float(MAX_RESOLUTION), float(DENSE_AUTO_MAX), float(DENOISE_MIN_NOISE)}


def test_every_number_in_the_reconstruct_help_is_a_value_of_the_tables():
    """A number typed into a help text (not generated from the tables) fails here as soon as the table changes."""
    # 0 and 1 are ranges ("[0, 1]", ">= 0"), 2 the 2x2x2 box, 3 the spacings of --outlier-radius's rule (o3drbf.pipeline).
    allowed = table_values() | {0.0, 1.0, 2.0, 3.0}
    for action in command("reconstruct")._actions:
        for token in NUMBER.findall(action.help or ""):
            value = float(token.rstrip(",").replace(",", ""))
            assert value in allowed, (action.option_strings, token, action.help)


def test_solver_help_says_where_auto_switches():
    help_text = option(command("reconstruct"), "--solver").help
    assert f"dense up to {DENSE_AUTO_MAX:,} constraints" in help_text


def test_automatic_sizes_in_the_help_are_the_table():
    rec = command("reconstruct")
    a = AUTO_SIZES
    assert f"points / {a['points_per_constraint']}, between {a['min_constraints']:,} and {a['max_constraints']:,}" in option(rec, "--surface-count").help
    resolution = option(rec, "--resolution").help
    assert f"at most {MAX_RESOLUTION}" in resolution and f"{a['min_resolution']} to {a['max_resolution']}" in resolution
    assert f"one tile per {TILE_DEFAULTS['points_per_tile']:,} points" in option(rec, "--tiles").help


def test_one_resolution_limit_for_the_options_and_the_viewer(monkeypatch):
    import o3drbf.solvers.base as base
    from o3drbf.cli.arguments import options_from_args

    monkeypatch.setattr(base, "available_memory", lambda: 64 * 2**30)  # the finest grid fits: only the limit is tested

    view = command("view")
    assert f"2..{MAX_RESOLUTION}" in option(view, "--resolution").help
    args = view.parse_args(["scan.json", "--resolution", str(MAX_RESOLUTION)])
    assert options_from_args(args, "view").validate().fit.extract.resolution == MAX_RESOLUTION
    with pytest.raises(ValueError, match="resolution"):
        options_from_args(view.parse_args(["scan.json", "--resolution", str(MAX_RESOLUTION + 1)]), "view").validate()
    with pytest.raises(ValueError, match="resolution"):
        ExtractOptions(resolution=MAX_RESOLUTION + 1).validate()


def test_public_defaults_are_the_table():
    """extract_mesh and the option groups default to DEFAULTS (extract_mesh's resolution is "auto", as the table says)."""
    assert inspect.signature(o3drbf.extract_mesh).parameters["resolution"].default == DEFAULTS["resolution"]
    assert Options().flat() == DEFAULTS
    for name, value in DEFAULTS.items():
        default = option(command("reconstruct"), "--" + name.replace("_", "-")).default if name not in API_ONLY else value
        assert default == value, name


def test_extract_mesh_auto_follows_the_constraint_spacing(monkeypatch):
    """extract_mesh(surface) meshes at auto_resolution of the surface's constraint spacing, as reconstruct does."""
    import o3drbf.extract as extract
    from o3drbf.synthetic.shapes import Sphere

    points, normals = Sphere(1.0).sample(800, seed=2)
    surface = o3drbf.reconstruct(points, normals, surface_count=300, resolution=16, robust=False).surface
    assert o3drbf.options.auto_resolution is extract.auto_resolution
    used = []

    class Stop(Exception):
        pass

    def grid_for(box, resolution=None, voxel_size=None, multiple=1):
        used.append(resolution)
        raise Stop

    monkeypatch.setattr(extract, "grid_for", grid_for)
    spacing_of_fit = surface.metadata["mean_spacing"]
    for spacing in (spacing_of_fit, 0.005, float("nan")):
        surface.metadata["mean_spacing"] = spacing
        with pytest.raises(Stop):
            extract.extract_mesh(surface)
    a = AUTO_SIZES
    assert used[0] == extract.auto_resolution(spacing_of_fit) == min(max(round(2 * a["cells_per_spacing"] / spacing_of_fit),
                                                                          a["min_resolution"]), a["max_resolution"])
    assert used[1:] == [a["max_resolution"], a["min_resolution"]]


def test_every_number_in_the_readme_option_table_is_a_value_of_the_tables():
    """The README's option table (tests/project/test_readme.py checks its options) says the same numbers as the code."""
    from conftest import REPO
    from o3drbf.options import RegistrationOptions

    text = (REPO / "README.md").read_text()
    start = text.index("| option | meaning | default |")
    table = text[start:text.index("\n\n", start)]
    allowed = table_values() | {0.0, 1.0, 2.0, 3.0, 100 * RegistrationOptions().min_gain}
    for row in table.splitlines()[2:]:
        for token in NUMBER.findall(re.sub(r"\]\(#[^)]*\)", "]", row).replace("x2x2", "")):
            assert float(token.rstrip(",").replace(",", "")) in allowed, (token, row)
