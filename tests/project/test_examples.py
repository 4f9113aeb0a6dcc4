"""Every public function and class of ``o3drbf`` (``o3drbf.__all__``) has a numpydoc Examples section, and it runs.

The examples are doctests: each one's printed lines are checked against what
it prints now, on small seeded inputs, all of them together in well under
half a minute.  The data names of ``__all__`` (``DEFAULTS``, ``KERNELS``)
have no docstring of their own: they are documented where they are defined
and used in the examples of :class:`o3drbf.Options` and
:func:`o3drbf.register_kernel`.
"""

from __future__ import annotations

import doctest
import inspect
import time

import pytest

import o3drbf

#: Names of ``o3drbf.__all__`` that are data, not a function or class (no docstring to carry an example).
DATA = {"DEFAULTS", "KERNELS"}

#: Beside ``o3drbf.__all__``: the main entry point of each subpackage.
ENTRY_POINTS = [
    "o3drbf.cameras.model:Camera",
    "o3drbf.cli.commands:main",
    "o3drbf.evaluation.compare:compare",
    "o3drbf.io.files:read_points",
    "o3drbf.mesh.metrics:mesh_report",
    "o3drbf.photo.pipeline:run_photos",
    "o3drbf.synthetic.shapes:Torus",
    "o3drbf.tiles.run:reconstruct_tiled",
    "o3drbf.viewers.session:view",
]


def public_objects():
    """``(name, object)`` for each function and class of ``o3drbf.__all__``."""
    return [(name, getattr(o3drbf, name)) for name in o3drbf.__all__ if name not in DATA]


def entry_points():
    import importlib

    found = []
    for spec in ENTRY_POINTS:
        module, name = spec.split(":")
        found.append((spec, getattr(importlib.import_module(module), name)))
    return found


def examples_of(obj) -> list[doctest.DocTest]:
    """The doctests of ``obj``'s own docstring (not its methods')."""
    return [t for t in doctest.DocTestFinder(recurse=False).find(obj, obj.__name__) if t.examples]


def test_the_data_names_are_data():
    for name in DATA:
        value = getattr(o3drbf, name)
        assert not (inspect.isfunction(value) or inspect.isclass(value)), name


@pytest.mark.parametrize("name, obj", public_objects() + entry_points(), ids=lambda x: x if isinstance(x, str) else "")
def test_each_public_name_has_an_examples_section(name, obj):
    doc = inspect.getdoc(obj) or ""
    assert "\nExamples\n--------\n" in doc, f"{name}: no numpydoc 'Examples' section"
    assert examples_of(obj), f"{name}: its Examples section has no runnable >>> example"


def run_examples(objects) -> list[str]:
    """Run every example of ``objects``; one line per failed example ('' list when all pass)."""
    failures = []
    for name, obj in objects:
        for test in examples_of(obj):
            runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
            out = []
            runner.run(test, out=out.append)
            if runner.failures:
                failures.append(f"{name}: " + " ".join("".join(out).split())[:800])
    return failures


@pytest.mark.slow
def test_the_examples_run_and_print_what_they_show():
    t0 = time.perf_counter()
    failures = run_examples(public_objects() + entry_points())
    seconds = time.perf_counter() - t0
    assert not failures, "\n".join(failures)
    assert seconds < 30, f"the examples took {seconds:.0f} s (keep them small: under about 30 s together)"
