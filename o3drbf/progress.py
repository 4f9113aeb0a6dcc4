"""One rule for progress bars: on when asked, off when ``O3DRBF_NO_PROGRESS=1``.

Bars go to stderr through tqdm; log records are routed through
:func:`tqdm.contrib.logging.logging_redirect_tqdm` by the command line so
the two never interleave.
"""

from __future__ import annotations

import os

__all__ = ["progress_bar", "progress_enabled"]


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
