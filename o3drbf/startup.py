"""Start-up: Open3D's Plotly/Dash helpers loaded when first used, not at ``import open3d``.

``import open3d`` (0.17-0.19) imports ``open3d.visualization.draw_plotly``,
which imports Dash and Plotly, for three functions o3drbf never calls; that is
much of the import's time.  :func:`defer_open3d_plotly` puts a stand-in for
that module in ``sys.modules`` before Open3D is imported: the stand-in's
functions (and any other attribute) import the real module on first use, so
``open3d.visualization.draw_plotly(...)`` still works in a program that also
imports o3drbf.  Nothing is done when Open3D is already imported.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
from contextlib import contextmanager
import threading
import types

__all__ = ["defer_open3d_plotly", "PLOTLY_MODULE", "no_hugepage_advice", "HUGEPAGE_VARIABLE",
           "prefer_numba_workqueue", "THREADING_PRIORITY", "ready_numba_in_background", "when_imported"]

#: NumPy's environment variable (read when NumPy is imported): "0" stops it advising the kernel to back
#: large arrays with transparent huge pages.
HUGEPAGE_VARIABLE = "NUMPY_MADVISE_HUGEPAGE"

#: Numba's threading layers in the order o3drbf tries them (Numba's own default starts with TBB).
THREADING_PRIORITY = ("workqueue", "omp", "tbb")

#: The Open3D module that imports Dash and Plotly.
PLOTLY_MODULE = "open3d.visualization.draw_plotly"
_FUNCTIONS = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _real():
    """Import the real module in place of the stand-in (once), and point ``open3d.visualization`` at it."""
    module = sys.modules.get(PLOTLY_MODULE)
    if module is not None and not getattr(module, "__o3drbf_stand_in__", False):
        return module
    sys.modules.pop(PLOTLY_MODULE, None)
    real = importlib.import_module(PLOTLY_MODULE)
    package = sys.modules.get("open3d.visualization")
    if package is not None:
        for name in _FUNCTIONS:
            if hasattr(real, name):
                setattr(package, name, getattr(real, name))
    return real


def _forward(name: str):
    def call(*args, **kwargs):
        return getattr(_real(), name)(*args, **kwargs)

    call.__name__ = name
    call.__doc__ = f"Open3D's ``{name}`` (its module imported on first call)."
    return call


def defer_open3d_plotly() -> bool:
    """Install the stand-in for :data:`PLOTLY_MODULE` unless Open3D is already imported.

    Returns
    -------
    bool
        Whether the stand-in was installed.
    """
    if "open3d" in sys.modules or PLOTLY_MODULE in sys.modules:
        return False
    stand_in = types.ModuleType(PLOTLY_MODULE, "Stand-in: the real module is imported on first use.")
    stand_in.__o3drbf_stand_in__ = True
    for name in _FUNCTIONS:
        setattr(stand_in, name, _forward(name))

    def attribute(name: str):
        if name.startswith("__"):  # the import system's own probes (__path__, __spec__...) must not load it
            raise AttributeError(name)
        return getattr(_real(), name)

    stand_in.__getattr__ = attribute
    sys.modules[PLOTLY_MODULE] = stand_in
    return True


def no_hugepage_advice() -> bool:
    """Set ``NUMPY_MADVISE_HUGEPAGE=0`` unless it is set already or NumPy is imported; True when set here.

    Called by the command line before anything imports NumPy.  A dense fit allocates its matrices
    (a gigabyte at 10,000 constraints) once and fills them at once; with NumPy's huge-page advice
    and the kernel's usual ``defrag=madvise`` setting, each first touch of those pages may wait while
    the kernel compacts memory to make huge pages, which on a machine whose memory other jobs have
    fragmented costs more system time than the huge pages save (benchmarks/recorded/scan_speed.md).
    A user's own setting of the variable is kept; a program that imported NumPy first is left alone.
    """
    import os

    if HUGEPAGE_VARIABLE in os.environ or "numpy" in sys.modules:
        return False
    os.environ[HUGEPAGE_VARIABLE] = "0"
    return True


def prefer_numba_workqueue() -> bool:
    """Make Numba try its own "workqueue" threads first, unless the user chose a threading layer.

    With the OpenMP layer, the solve (OpenBLAS) and the compiled sums both slow down next to
    Open3D's OpenMP runtime (docs/data/design-measurements.md, "Numba's threading layer"), and an
    old system TBB makes Numba print a warning the first time any parallel function runs.  Called
    when ``o3drbf`` is imported, so it holds for every compiled module whichever runs first; set
    through the environment (read when Numba is imported) when Numba is not imported yet, else on
    its configuration.  workqueue must not be entered from two Python threads at once: o3drbf calls
    its parallel functions from one thread at a time.

    Returns
    -------
    bool
        Whether the order was set here (False when ``NUMBA_THREADING_LAYER`` or
        ``NUMBA_THREADING_LAYER_PRIORITY`` is set already).
    """
    import os

    if "NUMBA_THREADING_LAYER" in os.environ or "NUMBA_THREADING_LAYER_PRIORITY" in os.environ:
        return False
    os.environ["NUMBA_THREADING_LAYER_PRIORITY"] = " ".join(THREADING_PRIORITY)
    numba = sys.modules.get("numba")
    if numba is not None:  # imported before o3drbf: its configuration has read the environment already
        numba.config.THREADING_LAYER_PRIORITY = list(THREADING_PRIORITY)
    return True


_numba_ready: threading.Thread | None = None
_numba_ready_lock = threading.Lock()


def _ready_numba() -> None:
    try:
        from numba.core.compiler_lock import global_compiler_lock
        from numba.core.registry import cpu_target

        with global_compiler_lock:  # as Numba's own compilation holds it
            cpu_target.typing_context.refresh()
            cpu_target.target_context.refresh()
    except Exception:  # noqa: BLE001 - the first compiled function readies Numba itself, and says what fails
        pass


def ready_numba_in_background() -> threading.Thread | None:
    """Ready Numba's compiler in a daemon thread, once per process, while the caller goes on.

    Numba's first compiled function of a process (even one loaded from its cache) waits while
    Numba installs its CPU target's typing and lowering registries, which imports most of Numba's
    own modules.  :func:`o3drbf.reconstruct` starts this thread as it begins, so that the
    installation runs beside its first stages (the input's checks, the scans' registration, the
    outlier tests), whose NumPy, SciPy and Open3D calls leave the interpreter's lock free part of
    the time.  The thread holds Numba's compiler lock, as Numba's compilation does; a compiled
    function called meanwhile waits for it.

    Returns
    -------
    threading.Thread or None
        The thread (the same one on every call), or None without Numba.
    """
    global _numba_ready
    with _numba_ready_lock:  # (reconstructions in several threads start one)
        if _numba_ready is None:
            try:
                import numba  # noqa: F401
            except ImportError:
                return None
            _numba_ready = threading.Thread(target=_ready_numba, name="o3drbf-numba-ready", daemon=True)
            _numba_ready.start()
    return _numba_ready


class _Then(importlib.abc.Loader):
    """A module's own loader, then ``callback(module)`` once the module has run (anything else: the loader's)."""

    def __init__(self, loader, callback):
        self._loader, self._callback = loader, callback

    def create_module(self, spec):
        return self._loader.create_module(spec)

    def exec_module(self, module):
        self._loader.exec_module(module)
        self._callback(module)

    def __getattr__(self, name):
        return getattr(self._loader, name)


class _AfterImport(importlib.abc.MetaPathFinder):
    def __init__(self, name: str, callback):
        self.name, self.callback, self.busy = name, callback, False

    def find_spec(self, fullname, path, target=None):
        if fullname != self.name or self.busy:
            return None
        self.busy = True  # the other finders find it
        try:
            spec = importlib.util.find_spec(fullname)
        finally:
            self.busy = False
        if spec is not None and spec.loader is not None:
            spec.loader = _Then(spec.loader, self.callback)
        return spec


@contextmanager
def when_imported(name: str, callback):
    """Within the block, ``callback(module)`` runs as soon as top-level module ``name`` is imported (at once
    when it already is).  The command line sets Open3D's verbosity this way, without importing Open3D
    itself: most runs never need it, and its import is a large part of a short run.

    Examples
    --------
    >>> seen = []
    >>> with when_imported("json", lambda module: seen.append(module.__name__)):
    ...     import json
    >>> seen
    ['json']
    """
    if name in sys.modules:
        callback(sys.modules[name])
        yield
        return
    finder = _AfterImport(name, callback)
    sys.meta_path.insert(0, finder)
    try:
        yield
    finally:
        if finder in sys.meta_path:
            sys.meta_path.remove(finder)
