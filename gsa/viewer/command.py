"""`gsa view RESULT_DIR_OR_JSON`: the results page of a local result on 127.0.0.1 (gsa.viewer.local)."""

from __future__ import annotations

import shutil
import signal
import sys
import threading


def add_view_parser(subparsers) -> None:
    p = subparsers.add_parser("view", help="serve the results page of a local result on 127.0.0.1")
    p.add_argument(
        "result",
        help="result.json of `gsa align`, many.json of `gsa align-many`, or a folder with result.json, "
        "many.json or s0/, s1/, ...",
    )
    p.add_argument("--port", type=int, default=0, help="port (default: a free one)")
    p.set_defaults(func=cmd_view)


def cmd_view(args) -> int:
    from gsa.viewer.local import make_server  # lazy: building the parser stays cheap

    # SIGTERM ends it like Ctrl-C, and the previews it made go with it.
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(0))
    server, url = make_server(args.result, port=args.port)  # its ValueErrors print as one line
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    try:
        thread.start()
        print(url, flush=True)
        print("serving until interrupted (Ctrl-C)", file=sys.stderr, flush=True)
        thread.join()
    finally:
        if thread.is_alive():
            server.shutdown()
        server.server_close()
        shutil.rmtree(server.work_dir, ignore_errors=True)
    return 0
