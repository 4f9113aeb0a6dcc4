"""One rule for progress bars: on when asked, off when ``O3DRBF_NO_PROGRESS=1``; compiled code's own printing kept off the terminal.

Bars go to stderr through tqdm; log records are routed through
:func:`tqdm.contrib.logging.logging_redirect_tqdm` by the command line so
the two never interleave.  :func:`native_output_logged` catches what a
compiled library prints past Python (PoissonRecon's ``[WARNING] ... bad
average roots``) and logs it as one line.
"""

from __future__ import annotations

import contextlib
import logging
import os

__all__ = ["progress_bar", "progress_enabled", "native_output_logged"]


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
    from tqdm.auto import tqdm

    options.setdefault("leave", False)
    return tqdm(iterable, **options)
