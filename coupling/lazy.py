"""A package's public names imported on first use: the package's ``__init__`` holds a table
of where each name lives, and importing the package costs nothing until a name is read
(``workflows`` and ``pbm``: the command line imports both first)."""

import importlib
import sys
from collections.abc import Callable


def lazy_names(package: str, homes: dict[str, str]) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of ``package`` (its ``__name__``) whose names
    ``homes`` maps to the modules that define them. A name read once is kept in the
    package, so its module is imported once; an unknown name raises AttributeError as a
    module would."""
    module = sys.modules[package]

    def __getattr__(name: str) -> object:
        home = homes.get(name)
        if home is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(home), name)
        setattr(module, name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(module)) | set(getattr(module, "__all__", ())) | set(homes))

    return __getattr__, __dir__
