"""What a path is, said in one line where a plain "not found" or a late failure would mislead:
a loop of symbolic links, a link to nothing, a folder no rename can replace."""

from __future__ import annotations

import errno
import fcntl
import os
import struct
from pathlib import Path


def why_absent(path: str | Path, default: str) -> str:
    """Why ``path`` is not the file or folder wanted: a folder where a file is, a loop of symbolic
    links, a link to nothing, each said as such, else ``default`` ("odometry file not found")."""
    if os.path.isdir(path):
        return "is a folder, where a file is wanted"
    try:
        os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "a loop of symbolic links (a link that leads back to itself)"
        if os.path.islink(path):
            return f"a symbolic link to {os.readlink(path)}, which does not exist"
    return default


# Linux's inode flags (linux/fs.h): FS_IOC_GETFLAGS, and the flags that forbid a rename or removal.
_FS_IOC_GETFLAGS, _FS_IMMUTABLE_FL, _FS_APPEND_FL = 0x80086601, 0x10, 0x20


def unreplaceable(folder: str | Path) -> str | None:
    """Why an existing folder cannot be renamed away or removed (a mount point, the immutable or
    append-only flag), else None (also where the flags cannot be read)."""
    if os.path.ismount(folder):
        return "is a mount point; name a folder inside it"
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        try:
            flags = struct.unpack("i", fcntl.ioctl(fd, _FS_IOC_GETFLAGS, bytes(8))[:4])[0]
        finally:
            os.close(fd)
    except OSError:
        return None
    return "is immutable or append-only (chattr +i / +a)" if flags & (_FS_IMMUTABLE_FL | _FS_APPEND_FL) else None
