"""Temp files for atomic writes (temp file + rename) with the permissions of a normal file.

`tempfile.mkstemp` creates its file 0600 whatever the umask; renamed into place it would
leave every model, JSON and image the library writes readable by its owner only. The temp
file here gets 0666 & ~umask (0644 under the usual umask 022), as open() would give.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def current_umask() -> int:
    """The process umask, read without changing it where the kernel says it (Linux >= 4.7):
    os.umask's set-and-restore would briefly change it for every thread."""
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def mkstemp_for(path: Path) -> tuple[int, str]:
    """(fd, name) of a new temp file beside `path`, mode 0666 & ~umask (mkstemp's 0600 otherwise)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~current_umask())
    except BaseException:
        os.close(fd)
        Path(tmp).unlink(missing_ok=True)
        raise
    return fd, tmp
