"""A power cut, simulated: what of a written file is still on disk when the power goes, by the rules a journalling
file system keeps (ext4's ``data=ordered`` with delayed allocation, the common case).

A killed process loses nothing that reached the page cache; a power cut loses all that no ``fsync`` forced to
disk. :class:`PowerCut` records every ``os.fsync`` and ``os.replace`` of a writer (monkeypatched: the calls
still happen; a synced descriptor is known by its file's inode, whoever opened it) and answers what a reader finds
after the cut:

- a file's bytes up to its size at the last ``fsync`` of a descriptor of it (an append-only file keeps a prefix;
  a file never synced reads empty: delayed allocation had not even given its blocks a place);
- a rename only once the folder it was made in is synced afterwards (otherwise the folder still names what it
  named before, here: nothing, since each test writes into a fresh folder).

A ``syncfs`` of the file system (:func:`popcode_runtime.base.files.sync_file_system`, what a
:class:`~popcode_runtime.base.files.SyncBatch` commits with) counts as an ``fsync`` of every file and folder; with
``syncfs=False`` the model answers that the system has none, so the batch falls back to syncing file by file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from popcode_runtime.base import files

Inode = tuple[int, int]  # (st_dev, st_ino)


def _inode(stat: os.stat_result) -> Inode:
    return stat.st_dev, stat.st_ino


@dataclass
class PowerCut:
    """The log of a writer's syncs and renames, and what survives a power cut after them."""

    events: list[tuple[str, Inode, Inode | None]] = field(default_factory=list)  # (what, file, its folder)
    synced_size: dict[Inode, int] = field(default_factory=dict)  # file -> bytes on disk
    renamed_to: dict[Inode, Path] = field(default_factory=dict)  # file -> the name it was renamed to

    def install(self, monkeypatch: pytest.MonkeyPatch, syncfs: bool = True) -> PowerCut:
        real_fsync, real_replace, real_syncfs = os.fsync, os.replace, files.sync_file_system

        def fsync(descriptor: int) -> None:
            real_fsync(descriptor)
            stat = os.fstat(descriptor)
            self.events.append(("fsync", _inode(stat), None))
            self.synced_size[_inode(stat)] = stat.st_size

        def replace(source: str | os.PathLike, target: str | os.PathLike, **arguments: object) -> None:
            moved = _inode(os.stat(source))
            real_replace(source, target, **arguments)
            folder = Path(os.path.abspath(target)).parent
            self.events.append(("replace", moved, _inode(os.stat(folder))))
            self.renamed_to[moved] = Path(os.path.abspath(target))

        def sync_file_system(folder: Path) -> bool:
            if not syncfs or not real_syncfs(folder):
                return False
            self.events.append(("syncfs", (0, 0), None))
            for inode, path in self.renamed_to.items():
                if path.is_file() and _inode(path.stat()) == inode:
                    self.synced_size[inode] = path.stat().st_size
            return True

        monkeypatch.setattr(os, "fsync", fsync)
        monkeypatch.setattr(os, "replace", replace)
        monkeypatch.setattr(files, "sync_file_system", sync_file_system)
        return self

    def renames(self) -> list[tuple[int, Inode, Inode]]:
        """(position in the log, renamed file, its folder) of every rename."""
        return [(at, moved, folder) for at, (what, moved, folder) in enumerate(self.events)
                if what == "replace" and folder is not None]

    def unsafe_renames(self) -> list[str]:
        """Each rename that is not preceded by an ``fsync`` of the file itself or not followed by one of its folder:
        after a power cut it may leave an empty file, or none."""
        unsafe = []
        for at, moved, folder in self.renames():
            if ("fsync", moved, None) not in self.events[:at]:
                unsafe.append(f"rename {at}: the file was not synced before it")
            if ("fsync", folder, None) not in self.events[at + 1:]:
                unsafe.append(f"rename {at}: its folder was not synced after it")
        return unsafe

    def survivor(self, path: Path, journal_committed: bool = False, written_back: bool = False) -> bytes | None:
        """What a reader finds at ``path`` after a power cut now: None if the folder's entry for it is lost, else
        its bytes that reached the disk. ``journal_committed``: the file system's own periodic commit came just
        before the cut, so every rename made is on disk whatever was synced; ``written_back``: so did the page
        cache's writeback of this file's data (without it, data reaches the disk only by a sync). The two files of
        an ordering are asked with opposite ``written_back``: the system writes files back in no promised order."""
        if not path.is_file():
            return None
        inode = _inode(path.stat())
        durable = [at for at, moved, folder in self.renames() if moved == inode and (journal_committed or
                   {("fsync", folder, None), ("syncfs", (0, 0), None)} & set(self.events[at + 1:]))]
        if not durable:
            return None
        data = path.read_bytes()
        return data if written_back else data[:self.synced_size.get(inode, 0)]
