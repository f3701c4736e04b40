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
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import pytest

Inode = tuple[int, int]  # (st_dev, st_ino)


def _inode(stat: os.stat_result) -> Inode:
    return stat.st_dev, stat.st_ino


@dataclass
class PowerCut:
    """The log of a writer's syncs and renames, and what survives a power cut after them."""

    events: list[tuple[str, Inode, Inode | None]] = field(default_factory=list)  # (what, file, its folder)
    synced_size: dict[Inode, int] = field(default_factory=dict)  # file -> bytes on disk

    def install(self, monkeypatch: pytest.MonkeyPatch) -> PowerCut:
        real_fsync, real_replace = os.fsync, os.replace

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

        monkeypatch.setattr(os, "fsync", fsync)
        monkeypatch.setattr(os, "replace", replace)
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

    def survivor(self, path: Path) -> bytes | None:
        """What a reader finds at ``path`` after a power cut now: None if the folder's entry for it is lost, else
        its bytes that reached the disk."""
        if not path.is_file():
            return None
        inode = _inode(path.stat())
        durable = [at for at, moved, folder in self.renames()
                   if moved == inode and ("fsync", folder, None) in self.events[at + 1:]]
        if not durable:
            return None
        return path.read_bytes()[:self.synced_size.get(inode, 0)]
