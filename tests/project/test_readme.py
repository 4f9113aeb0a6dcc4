"""The README is true: its Python examples run as written, its option table is the parser's, its summary is a fresh run's."""

import re

import pytest

from conftest import REPO


def blocks(name: str = "README.md"):
    text = (REPO / name).read_text()
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_readme_starts_with_the_two_commands():
    text = (REPO / "README.md").read_text()
    first = re.search(r"```sh\n(.*?)```", text, flags=re.S).group(1)
    assert [line.split("#")[0].strip() for line in first.strip().splitlines()] == ["make demo", "make test"]


def test_readme_python_examples_run():
    code = blocks()
    assert len(code) >= 3
    for i, block in enumerate(code):
        exec(compile(block, f"README.md python block {i}", "exec"), {})


@pytest.mark.parametrize("page, least", [("docs/python.md", 3), ("docs/lidar.md", 1)])
def test_docs_python_examples_run(page, least):
    """docs/python.md holds the examples the README's guide leaves out, docs/lidar.md the lidar one; they run too."""
    code = blocks(page)
    assert len(code) >= least
    for i, block in enumerate(code):
        exec(compile(block, f"{page} python block {i}", "exec"), {})


def test_readme_is_a_short_guide_whose_inputs_exist():
    """At most 450 lines; every input it names is written by make demo / make samples, or is in ../shared/data."""
    import importlib.util

    from conftest import SHARED_DATA

    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 450
    spec = importlib.util.spec_from_file_location("generate", REPO / "samples" / "generate.py")
    generate = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generate)
    samples = set(generate.SAMPLES) | {"scan.ply", "points.ply", "cams.json", "scan.json", "reference.ply"}
    demo = (REPO / "samples" / "demo.py").read_text()
    commands = "\n".join(re.findall(r"```sh\n(.*?)```", text, flags=re.S))
    for name in re.findall(r"out/samples/([\w.]+)", commands):
        assert name in samples, name
    for name in re.findall(r"(?<![\w/])out/([\w.]+\.(?:ply|xyz|json))\b", commands):
        written = re.search(rf"-o out/{re.escape(name)}\b", commands) or f'"{name}"' in demo
        assert written, f"out/{name} is neither written by an earlier command nor by make demo"
    shared = re.findall(r"\.\./shared/data/([\w./-]+)", text)
    assert shared
    if SHARED_DATA.is_dir():
        for path in shared:
            assert (SHARED_DATA / path).exists(), path
    assert "bunny/data/bun.conf" not in text.replace("stanford_bunny/data/bun.conf", "")


def test_readme_option_table_matches_the_parser():
    from o3drbf.cli.commands import build_parser

    text = (REPO / "README.md").read_text()
    start = text.index("| option | meaning | default |")
    table = text[start:text.index("\n\n", start)]
    documented = set(re.findall(r"`(--?[a-z][a-z-]*)", table))
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices["reconstruct"]
    options = {s for a in sub._actions for s in a.option_strings if s not in ("-h", "--help", "-o", "--output")}
    options = {o for o in options if o not in ("--quiet", "--verbose")}  # shown as -q, -v
    assert documented == options, (documented - options, options - documented)
    assert all(a.help for a in sub._actions if a.option_strings), "every option has help text"


def summary_fields(text: str) -> list[str]:
    """The field names of an ``o3drbf reconstruct`` summary: each indented line's words before the column gap."""
    return [re.split(r"\s{2,}", line.strip())[0] for line in text.splitlines() if line.startswith("  ") and line.strip()]


def test_readme_summary_block_has_the_fields_of_a_fresh_run(tmp_path, capsys):
    """The README's summary (noisy range scans with cameras) lists the lines a fresh run of the same kind prints, in order."""
    import open3d as o3d

    from o3drbf.cli.commands import main
    from o3drbf.synthetic.scans import range_scans, write_scan_json

    text = (REPO / "README.md").read_text()
    block = re.search(r"\n```\n(o3drbf reconstruct: .*?)```", text, flags=re.S).group(1)
    torus = o3d.geometry.TriangleMesh.create_torus(0.6, 0.25, 48, 24)
    points, owner, cams = range_scans(torus, n_views=3, width=160, height=120, noise=0.01, seed=0)  # more points than constraints
    scan = write_scan_json(tmp_path / "scan.json", points, cams, owner)
    assert main(["reconstruct", str(scan), "-o", str(tmp_path / "mesh.ply"), "--resolution", "32"]) == 0
    fresh = capsys.readouterr().out
    assert "denoised" in summary_fields(fresh)
    assert summary_fields(block) == summary_fields(fresh)
