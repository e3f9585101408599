"""Progress bars of the commands, on stderr, shown only when stderr is a terminal.

Every command makes its bars here, so that they behave the same: in a log file, a pipe or a CI job
(stderr not a TTY) they are disabled, because tqdm's redraws would otherwise fill the log with one line
per update. Whether stderr is a TTY is looked up when a bar is made (tests and callers may swap
``sys.stderr``).

Two shapes, matching what the library functions take:

* :func:`iter_progress`: a ``progress(iterable, desc=..., unit=...) -> iterable`` callable (the
  georef pipeline and the comparison wrap their loops with it);
* :func:`counter`: a context manager yielding ``update(done, *rest)``, for functions that report how
  many items are done (``detect_batch``, ``evaluate``, ``write_site``, ``write_synth_images``).
"""
from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Any, Callable, Iterable, Iterator


def stderr_is_tty() -> bool:
    """True when the current ``sys.stderr`` is a terminal."""
    try:
        return bool(sys.stderr.isatty())
    except (AttributeError, ValueError):  # no stderr, or a closed one
        return False


def bar(iterable: Iterable | None = None, **kw: Any):
    """A tqdm bar on stderr (``leave=False``), disabled unless stderr is a terminal. ``kw``: tqdm's."""
    from tqdm import tqdm

    kw.setdefault("leave", False)
    return tqdm(iterable, file=sys.stderr, disable=not stderr_is_tty(), **kw)


def iter_progress() -> Callable[..., Iterable]:
    """``progress(iterable, **tqdm_kw)`` for the pipeline's loops (see module doc)."""
    return bar


@contextmanager
def counter(total: int, **kw: Any) -> Iterator[Callable[..., None]]:
    """A bar of ``total`` items; yields ``update(done, *ignored)`` that moves it to ``done``."""
    b = bar(total=total, **kw)

    def update(done: int, *_: Any) -> None:
        b.update(done - b.n)

    try:
        yield update
    finally:
        b.close()


__all__ = ["stderr_is_tty", "bar", "iter_progress", "counter"]
