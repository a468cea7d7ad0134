"""A function run in a process forked early, so that its imports are paid beside this
process's own work.

A command whose last step needs a heavy library (the design's figure: matplotlib, a third
of a second to import) can fork a process when it starts: the child imports the module
while the parent imports and computes on the other core, then waits, asleep, for the
arguments that the parent has only at the end, and runs the function on them while the
parent finishes its own last steps. :class:`Prepared` is that process; where fork is
missing it runs the function in this process, when it is started.

The child is forked before the parent starts threads of its own (a fork copies no thread,
and a lock held by one stays locked); it exits on its own when the parent closes the pipe
without sending work.
"""

from __future__ import annotations

import importlib
import multiprocessing
import signal
from typing import Any

__all__ = ["Prepared"]


class Prepared:
    """A process that imports ``module`` now and later runs one of its functions.

    ``ready()`` waits until the process has imported the module (so that a parallel step
    of this process that sizes itself to the free cores finds it asleep); ``start(name,
    *args)`` sends the call (the arguments are pickled); ``result()`` waits for its return
    value, or raises the exception it raised. Use it as a context manager:
    leaving it closes the pipe and reaps the process, whether or not a call was made.
    ``fork=False``, or a platform without fork, runs the call in this process at ``start``.
    """

    def __init__(self, module: str, fork: bool = True) -> None:
        self.module = module
        self._outcome: tuple[str, Any] | None = None
        self._process = None
        self._conn = None
        self._imported = False
        if fork and "fork" in multiprocessing.get_all_start_methods():
            context = multiprocessing.get_context("fork")
            self._conn, child = context.Pipe()
            self._process = context.Process(target=_serve, args=(module, child, self._conn), daemon=True)
            self._process.start()
            child.close()

    def ready(self) -> None:
        """Wait until the process has imported the module (at once without a process)."""
        if self._conn is None or self._imported:
            return
        try:
            self._conn.recv()  # the child's "imported", sent whether or not the import failed
        except (EOFError, OSError):
            self.close()  # gone: the call will run here
        self._imported = True

    def start(self, name: str, *args: Any) -> None:
        """Run ``module.name(*args)``: in the forked process, or here when there is none."""
        if self._outcome is not None:
            raise RuntimeError(f"{self.module}.{name}: this process already ran a call")
        if self._conn is None:
            self._outcome = _call(importlib.import_module(self.module), name, args)
            return
        try:
            self._conn.send((name, args))
            self._outcome = ("sent", None)
        except (BrokenPipeError, EOFError, OSError):
            # the child is gone (killed): run it here rather than lose the output
            self.close()
            self._outcome = _call(importlib.import_module(self.module), name, args)

    def result(self) -> Any:
        """The call's return value; its exception re-raised here."""
        if self._outcome is None:
            raise RuntimeError(f"{self.module}: result() before start()")
        if self._outcome[0] == "sent":
            self.ready()
            try:
                if self._conn is None:
                    raise EOFError
                self._outcome = self._conn.recv()
            except (EOFError, OSError):
                raise RuntimeError(f"the process running {self.module} ended without an answer") from None
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


def _call(module, name: str, args: tuple) -> tuple[str, Any]:
    try:
        return ("ok", getattr(module, name)(*args))
    except Exception as exc:  # noqa: BLE001 - handed to the caller, which re-raises it
        return ("error", exc)


def _serve(module_name: str, conn, parent_end) -> None:
    """The child: import, wait for one call, answer it. A failed import is the call's error."""
    # the parent's end, inherited by the fork: closed, so that the parent's exit reads as
    # the end of the pipe here; Ctrl-C is the parent's to handle (it then closes the pipe)
    parent_end.close()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    module, failure = None, None
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # noqa: BLE001 - reported as the call's outcome
        failure = exc
    try:
        conn.send(("imported", None))
        name, args = conn.recv()
    except (EOFError, OSError):
        return  # the parent closed without work
    outcome = ("error", failure) if module is None else _call(module, name, args)
    try:
        conn.send(outcome)
    except Exception as exc:  # noqa: BLE001 - an unpicklable value or error: say so in one line
        conn.send(("error", RuntimeError(f"{module_name}.{name}: {type(exc).__name__}: {exc}")))
    finally:
        conn.close()
