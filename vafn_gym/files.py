"""File helpers shared by every writer of models and checkpoints (no torch, no simulator)."""

from __future__ import annotations

import os
import secrets
from collections.abc import Callable
from pathlib import Path


def atomic_write(path: str | os.PathLike[str], write_fn: Callable[[Path], None]) -> Path:
    """Run ``write_fn(tmp)`` on a fresh temporary path in ``path``'s folder, then rename it onto ``path``.

    Either the complete new file replaces ``path`` or, if ``write_fn`` raises (or the process dies), ``path`` keeps its
    previous content and the temporary file is removed (a killed process may leave a hidden ``.<name>.*.tmp`` file).
    The temporary path keeps ``path``'s suffix, so writers that add a default suffix (SB3's ``save``) leave it as is.

    :param path: the file to (over)write; its folder is created if needed.
    :param write_fn: writes the whole file to the path it is given.
    :return: ``path`` as a ``Path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(8)}.tmp{path.suffix}")
    try:
        write_fn(tmp)
        # Flush to disk before the rename: otherwise a power loss can leave the renamed file empty.
        with open(tmp, "rb+") as file:
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path
