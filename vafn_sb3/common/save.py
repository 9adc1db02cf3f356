"""Model files on disk: SB3 zips written atomically and checked before loading; imports no algorithm.

:class:`AtomicSaveMixin` routes every algorithm's ``save`` through :func:`atomic_write` (a crash mid-write leaves the
previous file intact) and makes ``load`` reject truncated or incomplete zips with a ``ValueError`` naming the file. The
zip checks and size limits here are shared with the weights-only format (:mod:`vafn_sb3.common.serialization`).
"""

from __future__ import annotations

import io
import os
import zipfile
import zlib
from pathlib import Path
from typing import Any

import torch as th

from vafn_gym.files import atomic_write

__all__ = ["CONFIG_ENTRY", "MAX_JSON_ENTRY_BYTES", "MAX_MODEL_FILE_BYTES", "MAX_TENSOR_ENTRY_BYTES", "MAX_ZIP_ENTRIES",
           "POLICY_ENTRY", "VARIABLES_ENTRY", "AtomicSaveMixin", "check_file_size", "check_model_zip",
           "check_zip_directory", "check_zip_entries", "entry_limit", "sb3_zip_path"]

#: Entries of a weights-only file.
CONFIG_ENTRY = "config.json"
POLICY_ENTRY = "policy.pt"
VARIABLES_ENTRY = "variables.pt"
#: Largest model file (bytes), checked before the zip is opened.
MAX_MODEL_FILE_BYTES = 128 * 2**20
#: Most entries a model zip may list.
MAX_ZIP_ENTRIES = 64
#: Largest uncompressed JSON entry (a weights file's ``config.json``, an SB3 zip's ``data``), from the zip directory.
MAX_JSON_ENTRY_BYTES = 4 * 2**20
#: Largest uncompressed tensor entry of a weights file (``policy.pt``, ``variables.pt``), from the zip directory.
MAX_TENSOR_ENTRY_BYTES = 16 * 2**20


def sb3_zip_path(path: str | os.PathLike[str]) -> Path:
    """The file SB3's ``save`` writes for ``path``: ``path`` itself, or ``path.zip`` when it has no suffix."""
    path = Path(path)
    return path if path.suffix else Path(f"{path}.zip")


def check_model_zip(path: str | os.PathLike[str] | io.BufferedIOBase) -> None:
    """Raise a ``ValueError`` naming the file unless it is a complete, uncorrupted SB3 model zip.

    SB3 itself reports a zip without its ``data`` entry with a bare ``assert`` (which ``python -O`` removes). A missing
    file is left to SB3's ``load`` (``FileNotFoundError``).

    :param path: the model file (with or without its ``.zip`` suffix) or an open binary file.
    """
    if isinstance(path, io.BufferedIOBase):
        position = path.tell()
        try:
            check_zip_entries(path, repr(path), ("data", "policy.pth"))
        finally:
            path.seek(position)
        return
    file = Path(path)
    if not file.exists() and Path(f"{file}.zip").exists():
        file = Path(f"{file}.zip")
    if file.is_file():
        check_zip_entries(file, str(file), ("data", "policy.pth"))


def entry_limit(entry: str) -> int:
    """Largest uncompressed size (bytes) a model zip's ``entry`` may declare in the zip directory."""
    if entry in (CONFIG_ENTRY, "data"):
        return MAX_JSON_ENTRY_BYTES
    if entry in (POLICY_ENTRY, VARIABLES_ENTRY):
        return MAX_TENSOR_ENTRY_BYTES
    return MAX_MODEL_FILE_BYTES


def check_zip_directory(archive: zipfile.ZipFile, name: str) -> None:
    """``ValueError`` naming the file when its zip directory lists too many entries or one too large to inflate."""
    entries = archive.infolist()
    if len(entries) > MAX_ZIP_ENTRIES:
        raise ValueError(f"{name} lists {len(entries)} zip entries; a model file has at most {MAX_ZIP_ENTRIES}")
    for info in entries:
        if info.file_size > entry_limit(info.filename):
            raise ValueError(f"{name}: entry {info.filename!r} inflates to {info.file_size:,} bytes; at most "
                             f"{entry_limit(info.filename):,} are read (refused without inflating it)")


def check_file_size(path: Path, name: str) -> None:
    """``ValueError`` naming the file when it is larger than :data:`MAX_MODEL_FILE_BYTES`."""
    size = path.stat().st_size if path.is_file() else 0
    if size > MAX_MODEL_FILE_BYTES:
        raise ValueError(f"{name} is {size:,} bytes; a model file has at most {MAX_MODEL_FILE_BYTES:,}")


def check_zip_entries(file: Path | io.BufferedIOBase, name: str, required: tuple[str, ...],
                       bounded: bool = False) -> list[str]:
    """The zip's entry names after checking it is readable, complete and (``bounded``) within the size limits."""
    if bounded and isinstance(file, Path):
        check_file_size(file, name)
    try:
        with zipfile.ZipFile(file) as archive:
            if bounded:
                check_zip_directory(archive, name)
            entries = archive.namelist()
            corrupt = archive.testzip()
    except (zipfile.BadZipFile, zlib.error, EOFError) as error:
        raise ValueError(f"{name} is not a readable model file (truncated or corrupt zip): {error}") from error
    if corrupt is not None:
        raise ValueError(f"{name} is corrupt: entry {corrupt!r} fails its checksum")
    missing = [entry for entry in required if entry not in entries]
    if missing:
        raise ValueError(f"{name} is incomplete: no {', '.join(missing)} entry (an interrupted or partial save?)")
    return entries


class AtomicSaveMixin:
    """Algorithm mixin (first in the bases): atomic ``save``; ``load`` rejects broken files with a ValueError."""

    def save(
        self,
        path: str | os.PathLike[str] | io.BufferedIOBase,
        exclude: list[str] | None = None,
        include: list[str] | None = None,
    ) -> None:
        """SB3's ``save`` through :func:`atomic_write` (paths only): a crash mid-save keeps the previous file."""
        save = super().save  # type: ignore[misc]
        if isinstance(path, io.BufferedIOBase):
            save(path, exclude, include)
        else:
            atomic_write(sb3_zip_path(path), lambda tmp: save(tmp, exclude, include))

    @classmethod
    def load(
        cls,
        path: str | os.PathLike[str] | io.BufferedIOBase,
        env: Any = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> Any:
        """SB3's ``load`` (which unpickles: trusted files only) after :func:`check_model_zip`."""
        check_model_zip(path)
        return super().load(  # type: ignore[misc]
            path, env=env, device=device, custom_objects=custom_objects, print_system_info=print_system_info,
            force_reset=force_reset, **kwargs,
        )
