"""One signal policy for every command.

:func:`handled` (the CLI's ``main`` runs every command inside it) makes SIGINT, SIGTERM and SIGHUP raise
:class:`~coupling.errors.Interrupted` in the main thread: a KeyboardInterrupt, so every
``finally`` and ``except KeyboardInterrupt`` on the way out runs (a temporary removed, a
solver's ranks stopped) before ``main`` prints ``pbmdem: interrupted`` and exits with
128 + the signal's number (130, 143, 129). Without it SIGTERM and SIGHUP kill the process
where it stands, skipping every cleanup.

Python runs a signal handler between bytecodes, never inside a compiled kernel (numba, a
LAPACK call): the interrupt surfaces when the kernel returns, at the latest at the next
kernel call. Numba's dispatcher can then report it as a SystemError whose cause or context
is the interrupt; :func:`interrupt_in` finds it there.

:func:`deferred` holds a signal back over a few lines that must not be cut in half (a
temporary file written and renamed, or removed): the interrupt is raised when they end.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from coupling.errors import Interrupted

__all__ = ["deferred", "handled", "interrupt_in"]

#: The signals that end a command as interrupted.
SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))

_deferring = 0
_pending: list[int] = []


def _interrupt(signum, frame) -> None:
    if _deferring:
        _pending.append(signum)
        return
    raise Interrupted(signum)


@contextmanager
def handled() -> Iterator[None]:
    """Inside the block every signal of :data:`SIGNALS` raises :class:`Interrupted`, and
    SIGXFSZ (the file-size limit, ``ulimit -f``) is ignored, so that a write beyond the
    limit fails with EFBIG and is cleaned up like a full disk instead of killing the
    process. The previous handlers come back when it ends (a test calls ``main`` in
    pytest's process). Main thread only: elsewhere Python refuses a handler, and the
    defaults stay."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    chosen = dict.fromkeys(SIGNALS, _interrupt)
    if hasattr(signal, "SIGXFSZ"):
        chosen[signal.SIGXFSZ] = signal.SIG_IGN
    previous = {sig: signal.signal(sig, handler) for sig, handler in chosen.items()}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextmanager
def deferred() -> Iterator[None]:
    """Signals that arrive inside the block are raised as :class:`Interrupted` when it ends
    (the first one), also when the block raised: the user asked to stop either way. Only
    signals handled by :func:`handled`'s handler are held back."""
    global _deferring
    _deferring += 1
    try:
        yield
    finally:
        _deferring -= 1
        if not _deferring and _pending:
            signum = _pending[0]
            _pending.clear()
            raise Interrupted(signum)


def interrupt_in(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt (an :class:`Interrupted` or Ctrl-C's own) that ``exc`` is or
    was raised from or while handling (a compiled kernel's SystemError wraps it), else
    None."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None
