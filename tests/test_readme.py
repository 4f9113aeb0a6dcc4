"""The README's Python examples run as written."""

import re

from conftest import REPO


def blocks():
    text = (REPO / "README.md").read_text()
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
