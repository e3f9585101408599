"""Where per-image work runs: in this process, in a local process pool, or on a Dask cluster.

One interface for the three, :class:`Executor`::

    with make_executor(workers=4) as ex:                 # or scheduler="tcp://host:9786", or a Client
        for result in ex.imap(task, items):              # results in input order
            ...

``task`` is a picklable callable (a module-level function or an instance of a module-level class) and
``items`` small picklable values: for images, a path on storage every worker can read (a shared
folder on a cluster) and never the pixels, so that no image travels between processes and the caller
holds no image in memory. Results should be small and JSON-able (the detections of one image).

* :class:`SerialExecutor`: ``map`` in this process.
* :class:`PoolExecutor`: ``workers`` local processes (``spawn``: a fresh interpreter each, safe with
  OpenCV and threads). ``imap`` with one item per task.
* :class:`DaskExecutor`: a ``dask.distributed`` cluster, given a ``Client`` (used, not closed) or a
  scheduler address such as ``tcp://host:8786`` (connected here and closed on :meth:`close`). At most
  ``window`` tasks are in flight at once (default: 4 per worker thread), so a run over 100,000 images
  neither floods the scheduler nor keeps finished results waiting.

Dask is an optional dependency (``pip install cpdetect[dask]``): it is imported only when a
:class:`DaskExecutor` is made, so ``import cpdetect`` never imports it.

In every executor an exception raised by ``task`` reaches the caller from ``imap`` (remaining work
is cancelled); a task that wants the run to go on returns an error record instead.
"""
from __future__ import annotations

import logging
import os
from collections import deque
from typing import Any, Callable, Iterable, Iterator, Protocol, runtime_checkable

from .errors import UsageError

log = logging.getLogger(__name__)


@runtime_checkable
class Executor(Protocol):
    """Applies a task to items and yields the results in input order."""

    name: str

    def imap(self, task: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]: ...

    def close(self) -> None: ...


class _Closing:
    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        pass


class SerialExecutor(_Closing):
    """Runs each task in this process, one after the other."""

    name = "serial"

    def imap(self, task: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        return map(task, items)


class PoolExecutor(_Closing):
    """A pool of ``workers`` local processes (started on the first :meth:`imap`, ended by :meth:`close`)."""

    name = "processes"

    def __init__(self, workers: int):
        if workers < 1:
            raise UsageError(f"workers must be >= 1, got {workers}")
        self.workers = int(workers)
        self._pool = None

    def imap(self, task: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        if self._pool is None:
            import multiprocessing as mp

            self._pool = mp.get_context("spawn").Pool(self.workers)
        return self._pool.imap(task, items, chunksize=1)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.terminate()  # results were all consumed, or the run is being abandoned
            self._pool.join()
            self._pool = None


class DaskExecutor(_Closing):
    """Tasks on a ``dask.distributed`` cluster; see the module docstring.

    ``client``: a ``distributed.Client``, or a scheduler address (``tcp://host:port``) to connect to
    within ``connect_timeout`` seconds. ``window``: most tasks in flight (None: 4 per worker thread,
    at least 8).
    """

    name = "dask"

    def __init__(self, client: Any, window: int | None = None, connect_timeout: float = 10.0):
        try:
            import distributed
        except ModuleNotFoundError:
            raise UsageError("a Dask scheduler needs dask.distributed: pip install 'cpdetect[dask]'") from None
        self._owns = not isinstance(client, distributed.Client)
        if self._owns:
            address = str(client)
            try:
                client = distributed.Client(address, timeout=f"{connect_timeout}s", set_as_default=False)
            except (OSError, TimeoutError, ValueError) as exc:
                raise UsageError(f"cannot connect to the Dask scheduler at {address}: "
                                 f"{type(exc).__name__}: {exc}".rstrip(": ").splitlines()[0]) from None
        self.client = client
        self.window = window

    def _window(self) -> int:
        if self.window is not None:
            return max(1, int(self.window))
        try:
            threads = sum(self.client.nthreads().values())
        except Exception:  # a scheduler that does not answer now fails at submit with its own error
            threads = 0
        return max(8, 4 * threads)

    def imap(self, task: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        window = self._window()
        pending: deque = deque()
        it = iter(items)
        try:
            for item in it:
                pending.append(self.client.submit(task, item, pure=False))
                if len(pending) >= window:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:
            if pending:
                self.client.cancel(list(pending))

    def close(self) -> None:
        if self._owns and self.client is not None:
            self.client.close()
            self.client = None


def make_executor(workers: int = 1, scheduler: Any = None, connect_timeout: float = 10.0) -> Executor:
    """The executor for a request: Dask when ``scheduler`` (an address or a ``Client``) is given, else
    a process pool for ``workers`` > 1, else serial."""
    if scheduler is not None and scheduler != "":
        return DaskExecutor(scheduler, connect_timeout=connect_timeout)
    if workers < 1:
        raise UsageError(f"workers must be >= 1, got {workers}")
    return PoolExecutor(workers) if workers > 1 else SerialExecutor()


def available_cpus() -> int:
    """CPUs this process may run on (the affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


__all__ = ["Executor", "SerialExecutor", "PoolExecutor", "DaskExecutor", "make_executor", "available_cpus"]
