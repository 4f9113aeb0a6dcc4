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
