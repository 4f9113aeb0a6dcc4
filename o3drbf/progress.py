"""One rule for progress bars: on when asked, off when ``O3DRBF_NO_PROGRESS=1``; compiled code's own printing kept off the terminal.

Bars go to stderr through tqdm (its notebook bars inside IPython); log
records are written through ``tqdm.write`` by the command line
(:func:`logs_above_bars`) so the two never interleave.  :func:`native_output_logged` catches what a
compiled library prints past Python (PoissonRecon's ``[WARNING] ... bad
average roots``) and logs it as one line.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys

__all__ = ["progress_bar", "progress_enabled", "native_output_logged", "logs_above_bars"]


@contextlib.contextmanager
def native_output_logged(source: str, logger: str = "o3drbf"):
    """Catch what compiled code writes to the process's stdout and stderr (file descriptors 1 and 2) in the block.

    The text is logged at INFO as one line, ``"<source> printed: <text, whitespace collapsed>"``
    (shown by ``o3drbf -v``, dropped otherwise), instead of reaching the terminal.  Python's own
    writes to ``sys.stdout``/``sys.stderr`` in the block are caught too; where the descriptors
    cannot be duplicated the block runs unchanged.

    Parameters
    ----------
    source : str
        Who prints, for the log line (``"Open3D Poisson"``).
    logger : str
        The logger's name.

    Examples
    --------
    >>> import logging, os
    >>> with native_output_logged("a library"):
    ...     _ = os.write(2, b"[WARNING] chatter\\n   on two lines\\n")
    >>> logging.getLogger("o3drbf").isEnabledFor(logging.INFO)  # shown only at INFO (o3drbf -v)
    False
    """
    import ctypes
    import sys
    import tempfile

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass
    try:
        saved = [os.dup(1), os.dup(2)]
    except OSError:
        yield
        return
    libc = ctypes.CDLL(None)
    with tempfile.TemporaryFile() as caught:
        try:
            os.dup2(caught.fileno(), 1)
            os.dup2(caught.fileno(), 2)
            yield
        finally:
            libc.fflush(None)  # C stdio buffers (std::cout) into the file before the descriptors go back
            for stream in (sys.stdout, sys.stderr):
                try:
                    stream.flush()
                except (AttributeError, OSError, ValueError):
                    pass
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            caught.seek(0)
            text = " ".join(caught.read().decode("utf-8", "replace").split())
            if text:
                logging.getLogger(logger).info("%s printed: %s", source, text)


def progress_enabled(requested: bool) -> bool:
    """Whether a bar is shown: ``requested`` and not disabled by the environment."""
    return bool(requested) and os.environ.get("O3DRBF_NO_PROGRESS", "0") in ("", "0")


def progress_bar(requested: bool, iterable=None, **options):
    """A tqdm bar, or None (or the bare ``iterable``) when bars are off.

    Parameters
    ----------
    requested : bool
        The caller's ``progress`` option.
    iterable : iterable, optional
        Wrapped and returned (bare when bars are off).
    **options
        Passed to tqdm (``total``, ``desc``, ``unit``, ...); ``leave`` is False.
    """
    if not progress_enabled(requested):
        return iterable
    options.setdefault("leave", False)
    return _tqdm_class()(iterable, **options)


def _tqdm_class():
    """tqdm's notebook-aware bar inside IPython, else its plain one (without importing the notebook
    machinery, and asyncio with it, into a command-line process)."""
    if "IPython" in sys.modules:
        from tqdm.auto import tqdm
    else:
        from tqdm.std import tqdm
    return tqdm


class _BarSafeHandler(logging.StreamHandler):
    """Writes a log record with ``tqdm.write``: above any progress bar, which it moves down."""

    def emit(self, record):
        try:
            _tqdm_class().write(self.format(record), file=self.stream)
            self.flush()
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception:
            self.handleError(record)


@contextlib.contextmanager
def logs_above_bars(logger: logging.Logger | None = None):
    """Route ``logger``'s (default: the root logger's) console handlers through ``tqdm.write`` in the block.

    The first handler writing to ``sys.stdout`` or ``sys.stderr`` gives its stream,
    formatter and filters to one handler that writes above the progress bars; the
    other console handlers are left out and every handler is restored afterwards
    (what ``tqdm.contrib.logging.logging_redirect_tqdm`` does, without importing
    tqdm's notebook and asyncio parts).

    Examples
    --------
    >>> import logging
    >>> log = logging.getLogger("o3drbf.example")
    >>> log.addHandler(logging.StreamHandler(sys.stderr))
    >>> with logs_above_bars(log):
    ...     type(log.handlers[-1]).__name__
    '_BarSafeHandler'
    >>> type(log.handlers[-1]).__name__
    'StreamHandler'
    """
    logger = logging.root if logger is None else logger
    original = logger.handlers
    console = [h for h in original if isinstance(h, logging.StreamHandler) and getattr(h, "stream", None) in (sys.stdout, sys.stderr)]
    handler = _BarSafeHandler()
    if console:
        handler.setFormatter(console[0].formatter)
        handler.stream = console[0].stream
        for f in console[0].filters:
            handler.addFilter(f)
    logger.handlers = [h for h in original if h not in console] + [handler]
    try:
        yield
    finally:
        logger.handlers = original
