"""File helpers shared by every writer of models and checkpoints (no torch, no simulator)."""

from __future__ import annotations

import csv
import os
import secrets
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any


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


def write_csv_rows(rows: Sequence[Mapping[str, Any]], path: str | os.PathLike[str], missing: str = "") -> Path:
    """Write dict rows as one CSV file, atomically; the header is every key in order of first appearance.

    :param rows: the rows (at least one).
    :param path: the CSV file; its folder is created if needed.
    :param missing: written where a row lacks a column.
    :return: ``path`` as a ``Path``.
    """
    if not rows:
        raise ValueError(f"no rows to write to {path}")
    columns = list(dict.fromkeys(key for row in rows for key in row))

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=columns, restval=missing)
            writer.writeheader()
            writer.writerows(rows)

    return atomic_write(path, write)
