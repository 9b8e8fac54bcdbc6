"""Run a command with a small, really full-able disk: `unshare -Urm python fulldisk.py DISK SIZE CTL -- cmd...`.

In a user + mount namespace of its own (no root needed) it mounts a tmpfs of SIZE at DISK
(visible to the command only), starts the command, and obeys the control folder CTL (outside
the namespace's tmpfs, so the test sees it): a file `fill` there fills DISK to its last byte
(then it is renamed `filled`), a file `free` removes the filler (renamed `freed`). The network
namespace is the host's: the command's loopback ports are the test's.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path


def fill(disk: Path) -> None:
    with open(disk / ".filler", "ab", buffering=0) as fh:
        for chunk in (1 << 16, 4096, 1):
            try:
                while True:
                    fh.write(b"\0" * chunk)
            except OSError:
                pass


def main() -> None:
    disk, size, ctl = Path(sys.argv[1]), sys.argv[2], Path(sys.argv[3])
    cmd = sys.argv[sys.argv.index("--") + 1 :]
    disk.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(disk)], check=True)
    child = subprocess.Popen(cmd)
    signal.signal(signal.SIGTERM, lambda *a: (child.terminate(), sys.exit(0)))
    while child.poll() is None:
        if (ctl / "fill").exists():
            fill(disk)
            os.replace(ctl / "fill", ctl / "filled")
        if (ctl / "free").exists():
            (disk / ".filler").unlink(missing_ok=True)
            os.replace(ctl / "free", ctl / "freed")
        time.sleep(0.05)
    sys.exit(child.returncode)


if __name__ == "__main__":
    main()
