"""The conversion child process (service.worker.convert runs it): read a model file, write it in
another 3DGS format. Its memory (the whole model, and the writer's) is returned to the OS
when it exits, so the API process that started it stays small.

    python -m service.worker.convert_child SRC OUT FORMAT MAX_GAUSSIANS PARENT_PID

Exit 0: OUT written. Exit 3 (BAD_INPUT_EXIT): the model cannot be read,
{"detail": ...} on stdout. Anything else: a failure (its traceback on stderr).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

BAD_INPUT_EXIT = 3  # a model it cannot read: service.worker.convert answers 422


def main(argv: list[str]) -> int:
    src, out, fmt, max_gaussians, parent = argv
    from service.worker.runners import _die_with_parent

    _die_with_parent(int(parent))  # an API that dies takes its conversions with it

    from gsa.io.formats import read_model, write_model
    from gsa.io.ply import PlyError  # FormatError's base: read_model raises it for PLY files

    try:
        model = read_model(Path(src), max_gaussians=int(max_gaussians))
    except PlyError as exc:
        print(json.dumps({"detail": str(exc.problem)}))
        return BAD_INPUT_EXIT
    write_model(model, Path(out), fmt)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
