"""What the tests of the rewrite path share: a shipped results file to rewrite, its
content's digest, and what a rewrite must never leave beside it."""

import hashlib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "workflows/reference/validation/dem-dccc770e3c39f48c.h5"


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def leftovers(folder: Path) -> list[str]:
    """Temporaries, lock files and HDF5 in-memory names that reached the disk."""
    return sorted(p.name for p in folder.iterdir() if p.suffix in (".tmp", ".lock", ".mem"))


def shipped_copy(folder: Path) -> Path:
    """A copy of :data:`SHIPPED` in ``folder``, free to be rewritten."""
    path = folder / "results.h5"
    path.write_bytes(SHIPPED.read_bytes())
    return path
