"""File helpers shared by every writer of models and checkpoints (no torch, no simulator)."""

from __future__ import annotations

import csv
import os
import re
import secrets
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any


#: A temporary file of the older naming (no writer pid) older than this (s) was left by a killed save.
STALE_TEMP_S = 3600.0
_TEMP_TAG = re.compile(r"(?:(?P<pid>\d+)-)?[0-9a-f]{16}")


def _temp_path(path: Path) -> Path:
    """A fresh hidden temporary path beside ``path``: ``.<name>.<pid>-<random>.tmp<suffix>``."""
    return path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(8)}.tmp{path.suffix}")


def _pid_alive(pid: int) -> bool:
    """Whether a process with this pid runs on this machine (assumed so where that cannot be asked safely)."""
    if os.name != "posix":
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _is_stale_temp(candidate: Path, tag: str) -> bool:
    """Whether a temporary file with this tag was left by a writer that is gone."""
    match = _TEMP_TAG.fullmatch(tag)
    if match is None:
        return False
    if match["pid"] is not None:
        return not _pid_alive(int(match["pid"]))
    try:
        return time.time() - candidate.stat().st_mtime > STALE_TEMP_S
    except OSError:
        return False


def remove_stale_temps(path: str | os.PathLike[str]) -> list[Path]:
    """Remove the hidden temporary files that killed :func:`atomic_write` calls for ``path`` left behind.

    A temporary file is stale when the process that wrote it is gone (or, for files of the older naming without a pid,
    when it is older than ``STALE_TEMP_S``); a live writer's file is never touched. Errors are ignored.

    :param path: the target file whose folder is searched.
    :return: the files removed.
    """
    path = Path(path)
    prefix, suffix = f".{path.name}.", f".tmp{path.suffix}"
    removed = []
    try:
        candidates = [c for c in path.parent.iterdir() if c.name.startswith(prefix) and c.name.endswith(suffix)]
    except OSError:
        return removed
    for candidate in candidates:
        if _is_stale_temp(candidate, candidate.name[len(prefix) : len(candidate.name) - len(suffix)]):
            try:
                candidate.unlink()
            except OSError:
                continue
            removed.append(candidate)
    return removed


def atomic_write(path: str | os.PathLike[str], write_fn: Callable[[Path], None]) -> Path:
    """Run ``write_fn(tmp)`` on a fresh temporary path in ``path``'s folder, then rename it onto ``path``.

    Either the complete new file replaces ``path`` or, if ``write_fn`` raises (or the process dies), ``path`` keeps its
    previous content and the temporary file is removed. A killed process may leave a hidden ``.<name>.<pid>-*.tmp``
    file: the next save of ``path`` removes it (:func:`remove_stale_temps`). The temporary path keeps ``path``'s
    suffix, so writers that add a default suffix (SB3's ``save``) leave it as is.

    :param path: the file to (over)write; its folder is created if needed.
    :param write_fn: writes the whole file to the path it is given.
    :return: ``path`` as a ``Path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path)
    tmp = _temp_path(path)
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


def repository_commit(root: str | os.PathLike[str]) -> str:
    """The short HEAD commit of the git checkout at ``root``, with ``+dirty`` where tracked files differ from it (what
    a results file names as the code it came from)."""
    import subprocess

    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True)
    dirty = subprocess.run(["git", "diff", "--quiet", "HEAD"], cwd=root).returncode != 0
    return head.stdout.strip() + ("+dirty" if dirty else "")
