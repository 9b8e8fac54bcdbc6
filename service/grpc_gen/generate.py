"""Regenerate service/grpc_gen/ from proto/gsa/v1/alignment.proto.

    python -m service.grpc_gen.generate

protoc names the modules after the proto path (gsa/v1/...), which would
collide with the `gsa` library package, so the files are flattened here and
the one cross import is rewritten. tests/service/test_grpc.py regenerates into
a temp dir and fails if the committed files differ.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PROTO = "gsa/v1/alignment.proto"
FILES = ("alignment_pb2.py", "alignment_pb2.pyi", "alignment_pb2_grpc.py")


def generate(out_dir: Path) -> list[Path]:
    import tempfile

    import grpc_tools
    from grpc_tools import protoc

    include = Path(grpc_tools.__file__).parent / "_proto"
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        rc = protoc.main(["protoc", f"-I{ROOT / 'proto'}", f"-I{include}", f"--python_out={tmp}",
                          f"--pyi_out={tmp}", f"--grpc_python_out={tmp}", str(ROOT / "proto" / PROTO)])
        if rc != 0:
            raise RuntimeError(f"protoc failed with {rc}")
        written = []
        for name in FILES:
            text = (Path(tmp) / "gsa" / "v1" / name).read_text()
            text = text.replace("from gsa.v1 import alignment_pb2", "from service.grpc_gen import alignment_pb2")
            (out_dir / name).write_text(text)
            written.append(out_dir / name)
    return written


if __name__ == "__main__":
    for p in generate(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent):
        print(p)
