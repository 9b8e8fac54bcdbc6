"""A gaussforge decode in its own process: `python -m gsa.io.packed_child FORMAT` reads the
file's bytes on stdin and writes an INRIA PLY to stdout (exit 0), or the decoder's error to
stderr (exit 2). gaussforge 0.6.0 crashes (SIGSEGV) on some corrupt SOG archives; in a child
a crash is an error message, not the end of the CLI, the worker or the API process."""

from __future__ import annotations

import os
import sys


def main() -> int:
    import gaussforge

    data = sys.stdin.buffer.read()
    out = os.dup(1)  # the PLY goes here; fd 1 itself is silenced (gaussforge's SPZ debug line)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    result = gaussforge.GaussForge().convert(data, sys.argv[1], "ply")
    if "error" in result:
        sys.stderr.write(str(result["error"]))
        return 2
    with os.fdopen(out, "wb") as fh:
        fh.write(result["data"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
