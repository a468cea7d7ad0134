"""The project's exceptions, shared by every stage.

Library code raises these; only the CLI (``workflows.cli.main``) turns them into a message and
an exit code. Each message names the offending value and what would have been valid.
"""


def os_reason(exc: OSError) -> str:
    """What the file system said, in one line: the errno's text when there is one (HDF5's
    messages run over several lines and name temporary files), else the message itself."""
    import os

    if exc.errno:
        return os.strerror(exc.errno)
    return " ".join(str(exc).split()) or type(exc).__name__


def error_line(exc: BaseException) -> str:
    """A project error or a file-system refusal as the CLIs print it: one line, naming the
    path(s) the file system refused."""
    if isinstance(exc, OSError):
        where = " -> ".join(str(name) for name in (exc.filename, exc.filename2) if name)
        return os_reason(exc) + (f": {where}" if where else "")
    return str(exc)


class Interrupted(KeyboardInterrupt):
    """A signal asked the command to stop (SIGINT, SIGTERM, SIGHUP; :mod:`coupling.interrupts`).
    A KeyboardInterrupt, so that every ``except KeyboardInterrupt`` that cleans up after
    Ctrl-C (a solver's ranks stopped, a run marked interrupted) does the same for the others;
    ``exit_code`` is the shell's for a process the signal ended, 128 + its number."""

    def __init__(self, signum: int):
        self.signum = signum
        self.exit_code = 128 + signum
        super().__init__(f"signal {signum}")


class PbmDemError(Exception):
    """Base class of every error this project raises on purpose."""


class MissingExtraError(PbmDemError, ImportError):
    """An optional dependency is not installed: the message says what needs it and the
    ``pip install`` that brings it (e.g. pyvista, in the ``render`` extra)."""

    def __init__(self, module: str, extra: str, purpose: str):
        super().__init__(
            f"{purpose} needs {module}, which is not installed: pip install 'pbmdem[{extra}]'", name=module
        )


class ConfigError(PbmDemError, ValueError):
    """A configuration value, file, preset or key is invalid."""


class GeometryError(ConfigError):
    """The blender geometry is impossible or fails LIGGGHTS' mesh checks."""


class DeckError(PbmDemError):
    """A LIGGGHTS input deck could not be built from the configuration."""


class SolverNotFoundError(PbmDemError):
    """``liggghts`` or the MPI launcher is not installed."""


class SolverRunError(PbmDemError):
    """LIGGGHTS failed: an ERROR line, a non-zero exit or missing output.

    ``run_dir`` and ``log_tail`` tell the user where to look.
    """

    def __init__(self, message: str, run_dir=None, log_tail: str = ""):
        self.run_dir = run_dir
        self.log_tail = log_tail
        text = message
        if run_dir is not None:
            text += f"\n  run directory: {run_dir}"
        if log_tail:
            text += "\n  last lines of the solver log:\n" + "\n".join(
                "    " + line for line in log_tail.rstrip().splitlines()
            )
        super().__init__(text)


class DumpFormatError(PbmDemError, ValueError):
    """A LIGGGHTS dump file is malformed (the message names the file and line)."""


class TableError(PbmDemError, ValueError):
    """A velocity table is missing a dataset, has a wrong shape or invalid values."""


class OutputError(PbmDemError):
    """An output (run directory, result files, report) could not be written."""


class CacheError(PbmDemError):
    """A cache file is corrupt, foreign or could not be written."""


class ResultsError(CacheError):
    """A DEM results file's stored arrays contradict each other or the file's table (a state
    outside the grid, a run longer than the record, counts on another grid): the message
    names the file, the array and what would be valid. Not a ValueError, so that no
    ``except ValueError`` meant for a fit that lacks data turns it into a note."""


class ResourceLimitError(PbmDemError, ValueError):
    """An input would need more memory or time than the machine can give (the message
    carries the estimate, what is available and how to make the problem smaller)."""
