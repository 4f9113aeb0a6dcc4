"""The tests mirror the package, and the fast tier's slow marks still name real tests.

``tests/<subpackage>/test_<module>.py``: every folder of tests is a
subpackage of o3drbf (or ``project/``, the checks of the whole repository),
and every test file's name is unique, because ``tests/conftest.py`` keys the
slow marks (``SLOW_MODULES``, ``SLOW_TESTS``, ``SLOW_FIXTURES``) by file
name.  A mark whose file or test was renamed or moved would silently put a
slow test back into ``make test-fast``; so would a key written twice in the
table (Python keeps only the last).
"""

from __future__ import annotations

import ast
import collections
import re

import conftest
from conftest import REPO

TESTS = REPO / "tests"
#: Test folders that are not o3drbf subpackages.
OTHER_FOLDERS = {"project", "viewers"}


def _test_files():
    return sorted(p for p in TESTS.rglob("test_*.py") if "__pycache__" not in p.parts)


def test_test_folders_mirror_the_package():
    packages = {p.parent.name for p in (REPO / "o3drbf").glob("*/__init__.py")}
    folders = {p.parent.relative_to(TESTS).as_posix() for p in _test_files()} - {"."}
    assert folders <= packages | OTHER_FOLDERS, f"test folders with no o3drbf subpackage: {sorted(folders - packages - OTHER_FOLDERS)}"


def test_test_file_names_are_unique():
    names = collections.Counter(p.name for p in _test_files())
    assert [n for n, k in names.items() if k > 1] == []


def test_every_slow_mark_names_an_existing_test():
    files = {p.name: p.read_text(encoding="utf-8") for p in _test_files()}
    missing = [m for m in conftest.SLOW_MODULES if m not in files]
    for table in (conftest.SLOW_TESTS, conftest.SLOW_FIXTURES):
        for module, names in table.items():
            if module not in files:
                missing.append(module)
                continue
            missing += [f"{module}::{n}" for n in names if not re.search(rf"^\s*def {re.escape(n)}\(", files[module], re.M)]
    assert missing == [], f"slow marks in tests/conftest.py naming no test (renamed or moved?): {missing}"


def test_no_slow_mark_is_written_twice():
    tree = ast.parse((TESTS / "conftest.py").read_text(encoding="utf-8"))
    repeated = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "").startswith("SLOW_") for t in node.targets):
            if isinstance(node.value, ast.Dict):
                keys = collections.Counter(k.value for k in node.value.keys if isinstance(k, ast.Constant))
                repeated += [f"{node.targets[0].id}[{k!r}]" for k, n in keys.items() if n > 1]
    assert repeated == [], f"keys written twice in tests/conftest.py (only the last counts): {repeated}"
