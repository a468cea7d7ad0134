"""A function run in a process forked early, so that its imports are paid beside this
process's own work.

A command whose last step needs a heavy library (the design's figure: matplotlib, a third
of a second to import) can fork a process when it starts: the child imports the module
while the parent imports and computes on the other core, then waits, asleep, for the
arguments that the parent has only at the end, and runs the function on them while the
parent finishes its own last steps. :class:`Prepared` is that process.

Whatever goes wrong with the process, the call still runs: where fork is missing or fails,
where the arguments cannot be pickled, or where the process dies before it answers, it
runs in this process instead. Fork it early, before this process has threads of its own
doing work (numpy's idle BLAS threads are fork-safe): a fork copies no thread, and a lock
one held stays locked in the child. The child exits on its own when the parent closes the
pipe, with or without a call; Ctrl-C is the parent's to handle.
"""

from __future__ import annotations

import importlib
import multiprocessing
import pickle
import signal
from typing import Any

__all__ = ["Prepared"]

#: What a pipe whose other end is gone raises.
_GONE = (BrokenPipeError, EOFError, OSError)


class Prepared:
    """A process that imports ``module`` now and later runs one of its functions.

    ``ready()`` waits until the process has imported the module (so that a parallel step
    of this process that sizes itself to the free cores finds it asleep); ``start(name,
    *args)`` sends the call (the arguments are pickled); ``result()`` waits for its return
    value, or raises the exception it raised. Use it as a context manager: leaving it
    closes the pipe and reaps the process, whether or not a call was made. ``fork=False``
    runs the call in this process at ``start``.
    """

    def __init__(self, module: str, fork: bool = True) -> None:
        self.module = module
        self._call: tuple[str, tuple] | None = None
        self._outcome: tuple[str, Any] | None = None
        self._process = None
        self._conn = None
        self._imported = False
        if not (fork and "fork" in multiprocessing.get_all_start_methods()):
            return
        context = multiprocessing.get_context("fork")
        self._conn, child = context.Pipe()
        try:
            self._process = context.Process(target=_serve, args=(module, child, self._conn), daemon=True)
            self._process.start()
        except (OSError, AssertionError):  # no process to be had (limits; a daemon's child): run here
            self._process = None
            self._conn.close()
            self._conn = None
        finally:
            child.close()

    def ready(self) -> None:
        """Wait until the process has imported the module (at once without a process)."""
        if self._conn is None or self._imported:
            return
        try:
            self._conn.recv()  # the child's "imported", sent whether or not the import failed
        except _GONE:
            self.close()  # gone: the call will run here
        self._imported = True

    def start(self, name: str, *args: Any) -> None:
        """Run ``module.name(*args)``: in the forked process, or here when there is none."""
        if self._call is not None:
            raise RuntimeError(f"{self.module}.{name}: this process already ran a call")
        self._call = (name, args)
        if self._conn is not None:
            try:
                self._conn.send(self._call)  # pickled whole before anything is written
                return
            except (*_GONE, pickle.PicklingError, TypeError, AttributeError):
                self.close()  # gone, or arguments it cannot be sent: run it here
        self._outcome = _run(importlib.import_module(self.module), name, args)

    @property
    def pending(self) -> bool:
        """A call was started and its answer not yet collected."""
        return self._call is not None and self._outcome is None

    def result(self) -> Any:
        """The call's return value; its exception re-raised here."""
        if self._call is None:
            raise RuntimeError(f"{self.module}: result() before start()")
        if self._outcome is None:
            self.ready()
            try:
                if self._conn is None:
                    raise EOFError
                self._outcome = self._conn.recv()
            except _GONE:
                # the process died before it answered (killed, out of memory): run it here
                self.close()
                self._outcome = _run(importlib.import_module(self.module), *self._call)
        kind, value = self._outcome
        if kind == "error":
            raise value
        return value

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._process is not None:
            self._process.join(timeout=5)
            if self._process.is_alive():
                self._process.terminate()
                self._process.join()
            self._process = None

    def __enter__(self) -> Prepared:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _run(module, name: str, args: tuple) -> tuple[str, Any]:
    try:
        return ("ok", getattr(module, name)(*args))
    except Exception as exc:  # noqa: BLE001 - handed to the caller, which re-raises it
        return ("error", exc)


def _portable(outcome: tuple[str, Any], what: str) -> tuple[str, Any]:
    """``outcome`` if it survives pickling both ways (an exception whose constructor takes
    other arguments than it was given does not), else its error in one line."""
    try:
        pickle.loads(pickle.dumps(outcome))
        return outcome
    except Exception as exc:  # noqa: BLE001 - any failure means: send words instead
        value = outcome[1]
        problem = value if outcome[0] == "error" else exc
        return ("error", RuntimeError(f"{what}: {type(problem).__name__}: {problem}"))


def _serve(module_name: str, conn, parent_end) -> None:
    """The child: import, wait for one call, answer it. A failed import is the call's error."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # first: Ctrl-C is the parent's
    # the parent's handlers (coupling.interrupts) would print a traceback here: a group's
    # SIGTERM ends the child quietly, and the parent reports the interrupt
    for name in ("SIGTERM", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_DFL)
    # the parent's end, inherited by the fork: closed, so that the parent's exit reads as
    # the end of the pipe here
    parent_end.close()
    module, failure = None, None
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # noqa: BLE001 - reported as the call's outcome
        failure = exc
    try:
        conn.send(("imported", None))
        name, args = conn.recv()
        outcome = ("error", failure) if module is None else _run(module, name, args)
        conn.send(_portable(outcome, f"{module_name}.{name}"))
    except _GONE:
        return  # the parent closed the pipe (done, or failing): nothing to answer
    finally:
        conn.close()
