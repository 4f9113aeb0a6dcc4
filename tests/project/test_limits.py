"""Sizes a newcomer can read: no library function with more than ``MAX_PARAMETERS`` parameters and no module over
``MAX_LINES`` lines, in ``o3drbf/`` and ``viewers/`` (checked with :mod:`ast`, nothing imported).

Parameters are counted as written: every named one (``self`` and ``cls`` aside) and ``*args`` / ``**kwargs``.
Numba kernels (functions decorated with ``njit`` / ``numba.njit`` / ``jit``) are left out: compiled code takes
its arrays one by one.  A function that needs more takes an options object (``o3drbf.options``).
"""

from __future__ import annotations

import ast

from conftest import REPO

MAX_PARAMETERS = 10
MAX_LINES = 900
ROOTS = ("o3drbf", "viewers")


def _modules():
    for root in ROOTS:
        for path in sorted((REPO / root).rglob("*.py")):
            if "__pycache__" not in path.parts:
                yield path


def _numba(node) -> bool:
    for deco in node.decorator_list:
        target = deco.func if isinstance(deco, ast.Call) else deco
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in ("njit", "jit", "vectorize", "guvectorize", "stencil"):
            return True
    return False


def parameter_count(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Named parameters (``self`` / ``cls`` aside), plus one each for ``*args`` and ``**kwargs``."""
    a = node.args
    named = [p.arg for p in (*a.posonlyargs, *a.args, *a.kwonlyargs) if p.arg not in ("self", "cls")]
    return len(named) + (a.vararg is not None) + (a.kwarg is not None)


def too_many_parameters(limit: int = MAX_PARAMETERS) -> list[str]:
    found = []
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not _numba(node):
                count = parameter_count(node)
                if count > limit:
                    found.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name} ({count} parameters)")
    return found


def too_long(limit: int = MAX_LINES) -> list[str]:
    found = []
    for path in _modules():
        lines = len(path.read_text(encoding="utf-8").splitlines())
        if lines > limit:
            found.append(f"{path.relative_to(REPO)} ({lines} lines)")
    return found


def test_no_library_function_takes_more_than_ten_parameters():
    assert too_many_parameters() == [], "take an options object (o3drbf.options) instead of a long parameter list"


def test_no_module_is_over_900_lines():
    assert too_long() == [], "split the module along its seams"


def test_the_checks_see_what_they_count():
    """The counting itself: a made-up function and the numba exemption (against hand counts)."""
    tree = ast.parse("def f(self, a, b=1, *c, d, e=2, **g): pass\n@numba.njit(cache=True)\ndef k(a, b): pass\n@njit\ndef m(a): pass\n")
    f, k, m = tree.body
    assert parameter_count(f) == 6 and not _numba(f) and _numba(k) and _numba(m)
    assert any(name.startswith("o3drbf/cli/") for name in (str(p.relative_to(REPO)) for p in _modules()))
