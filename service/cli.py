"""CLI verbs for the service: serve, worker, submit, status, wait, fetch.

gsa/cli.py wires them lazily:

    from service.cli import add_service_parsers
    add_service_parsers(subparsers)    # each sets func=handler; handler(args) -> exit code
"""

from __future__ import annotations

import argparse
import json
import os
import sys


def add_service_parsers(subparsers) -> None:
    p = subparsers.add_parser("serve", help="run the HTTP (and optionally gRPC) API; no Redis = embedded mode")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--grpc-port", type=int, help="also serve gRPC on this port")
    p.add_argument("--grpc-host", help="gRPC bind address (default $GSA_GRPC_HOST or 127.0.0.1, as --host)")
    p.add_argument(
        "--redis-url",
        help="Redis URL (default $GSA_REDIS_URL); none = embedded worker + SQLite",
    )
    p.add_argument(
        "--storage-root",
        help="local storage folder (default $GSA_STORAGE_ROOT or ./gsa-data)",
    )
    p.add_argument("--workers", type=int, help="embedded-mode worker threads")
    p.add_argument(
        "--no-auth",
        action="store_true",
        help="DEV ONLY: accept requests without an API key",
    )
    p.add_argument("--log-level", default="info")
    p.set_defaults(func=cmd_serve)

    p = subparsers.add_parser("worker", help="run a queue worker (needs Redis)")
    p.add_argument("--redis-url", help="Redis URL (default $GSA_REDIS_URL)")
    p.add_argument("--storage-root")
    p.add_argument("--burst", action="store_true", help="exit when the queue is empty")
    p.add_argument("--name")
    p.set_defaults(func=cmd_worker)

    def client_args(p):
        p.add_argument("--server", default=os.environ.get("GSA_SERVER", "http://127.0.0.1:8000"))
        p.add_argument(
            "--api-key",
            default=os.environ.get("GSA_API_KEY"),
            help="default $GSA_API_KEY",
        )

    p = subparsers.add_parser("submit", help="upload models to a server and create an alignment job")
    p.add_argument(
        "source",
        nargs="+",
        help="source model(s): .ply or .zip of images; several = multi-model",
    )
    p.add_argument("--target", required=True, help="target (reference) model")
    p.add_argument("--options", default="{}", help="JSON object of alignment options")
    p.add_argument("--stages", help="auto (default), coarse or coarse,fine")
    p.add_argument("--idempotency-key")
    p.add_argument("--webhook-url")
    p.add_argument("--wait", action="store_true", help="wait for the result")
    client_args(p)
    p.set_defaults(func=cmd_submit)

    for name, helptext in (
        ("status", "show a job"),
        ("wait", "wait until a job finishes"),
    ):
        p = subparsers.add_parser(name, help=helptext)
        p.add_argument("job_id")
        if name == "wait":
            p.add_argument("--timeout", type=float)
        client_args(p)
        p.set_defaults(func=cmd_status if name == "status" else cmd_wait)

    p = subparsers.add_parser("fetch", help="download a job's artifacts")
    p.add_argument("job_id")
    p.add_argument("names", nargs="*", help="artifact names, e.g. result.json (default: all)")
    p.add_argument("--out", default=".", help="output folder")
    client_args(p)
    p.set_defaults(func=cmd_fetch)
    _intermixed(p)  # `gsa fetch JOB --out DIR result.json`: names may follow the options


def _intermixed(parser: argparse.ArgumentParser) -> None:
    """Let this subparser's positionals come after its options.

    argparse fills `job_id` and an empty nargs="*" `names` from the first run of
    positionals, so in `fetch JOB --out DIR result.json` the name was "unrecognized".
    The top-level parser (gsa/cli.py) hands a subcommand's arguments to
    subparser.parse_known_args, which this routes through parse_known_intermixed_args
    (that calls parse_known_args again itself: the flag lets the inner call through)."""

    def parse_known_args(args=None, namespace=None):
        if getattr(parser, "_in_intermixed", False):
            return argparse.ArgumentParser.parse_known_args(parser, args, namespace)
        parser._in_intermixed = True
        try:
            return argparse.ArgumentParser.parse_known_intermixed_args(parser, args, namespace)
        finally:
            parser._in_intermixed = False

    parser.parse_known_args = parse_known_args


# Flags of `gsa serve` / `gsa worker` -> the Settings field each one sets.
_FLAG_SETTINGS = {
    "redis_url": "redis_url",
    "storage_root": "storage_root",
    "grpc_port": "grpc_port",
    "grpc_host": "grpc_host",
    "workers": "embedded_workers",
    "no_auth": "auth_disabled",
}


def _settings(args):
    """The process's one settings object, made and validated at start-up: the environment's
    GSA_* values, with the flags given on the command line over them."""
    from service.settings import Settings

    given = {field: getattr(args, flag) for flag, field in _FLAG_SETTINGS.items() if getattr(args, flag, None)}
    return Settings(**given)


def cmd_serve(args) -> int:
    # Lazy imports here and in cmd_worker: every `gsa` command registers these
    # verbs, so the server stack (FastAPI, uvicorn, RQ) loads only when used.
    import logging

    import uvicorn

    from service.api.app import create_app
    from service.logs import configure_logging

    settings = _settings(args)
    configure_logging(args.log_level, settings.log_format)
    mode = "embedded (SQLite + in-process worker)" if settings.embedded else f"distributed (Redis {settings.redis_url})"
    if settings.log_format == "json":
        logging.getLogger("gsa.serve").warning("gsa serve: %s; http://%s:%s", mode, args.host, args.port)
    else:
        print(f"gsa serve: {mode}; http://{args.host}:{args.port}", file=sys.stderr, flush=True)
    # JSON logs: uvicorn's own loggers go through the root handler (no text lines of its own),
    # and its access log is left off: gsa.api.access writes one line per request with its id.
    json_logs = settings.log_format == "json"
    uvicorn.run(
        create_app(settings),
        host=args.host,
        port=args.port,
        log_level=args.log_level,
        timeout_graceful_shutdown=5,
        **({"log_config": None, "access_log": False} if json_logs else {}),
    )
    return 0


def cmd_worker(args) -> int:
    from service.logs import configure_logging
    from service.worker.runners import run_rq_worker

    settings = _settings(args)
    configure_logging("INFO", settings.log_format)
    run_rq_worker(burst=args.burst, name=args.name, settings=settings)
    return 0


def _client(args):
    from gsa.client import GSAClient

    return GSAClient(args.server, args.api_key)


def _print(obj) -> None:
    print(json.dumps(obj, indent=2))


def _progress(job) -> None:
    print(
        f"{job['state']:>9} {job.get('stage') or '':<12} {100 * job.get('progress', 0):5.1f}%",
        file=sys.stderr,
        flush=True,
    )


EXIT_UNREACHABLE = 3  # no answer from the server (1: it answered an error, or the job failed)
EXIT_BROKEN_PIPE = 128 + 13  # what a shell reports for a process ended by SIGPIPE


def _errors(fn):
    """Client verbs end with one clear line, never a traceback: the server's
    problem (exit 1), the server not reachable (exit 3), or the reader of our
    output gone (`gsa status J | head -1`: exit 141, nothing printed)."""

    def wrapped(args) -> int:
        import httpx

        from gsa.client import GSAError, ServiceUnreachable

        try:
            try:
                rc = fn(args)
            finally:
                sys.stdout.flush()  # a closed pipe shows up here, not at interpreter exit
            return rc
        except BrokenPipeError:
            _silence_stdout()
            return EXIT_BROKEN_PIPE
        except GSAError as exc:
            print(f"gsa: error: {exc}", file=sys.stderr)  # one line: title (status): detail (request id)
            _print_quietly(exc.problem)
            return 1
        except ServiceUnreachable as exc:
            print(f"gsa: {exc}", file=sys.stderr)
            return EXIT_UNREACHABLE
        except httpx.HTTPError as exc:  # a read timeout, a connection dropped mid-answer, ...
            reason = str(exc) or type(exc).__name__
            print(f"gsa: request to {args.server} failed: {reason}", file=sys.stderr)
            return EXIT_UNREACHABLE

    return wrapped


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush does not raise
    BrokenPipeError again ("Exception ignored ... Broken pipe")."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


def _print_quietly(obj) -> None:
    try:
        _print(obj)
        sys.stdout.flush()
    except BrokenPipeError:
        _silence_stdout()


@_errors
def cmd_submit(args) -> int:
    options = json.loads(args.options)
    if args.stages:
        options["stages"] = args.stages.split(",")
    with _client(args) as c:
        job = c.submit(
            args.source,
            args.target,
            options,
            webhook_url=args.webhook_url,
            idempotency_key=args.idempotency_key,
        )
        if args.wait:
            job = c.wait(job["id"], on_progress=_progress, raise_on_failure=False)
    _print(job)
    return 0 if job["state"] in ("queued", "running", "succeeded") else 1


@_errors
def cmd_status(args) -> int:
    with _client(args) as c:
        _print(c.status(args.job_id))
    return 0


@_errors
def cmd_wait(args) -> int:
    with _client(args) as c:
        job = c.wait(
            args.job_id,
            timeout=args.timeout,
            on_progress=_progress,
            raise_on_failure=False,
        )
    _print(job)
    return 0 if job["state"] == "succeeded" else 1


@_errors
def cmd_fetch(args) -> int:
    with _client(args) as c:
        if not args.names:
            # A job with nothing to fetch (failed, cancelled, not finished) says so and fails:
            # it used to exit 0 having printed and written nothing.
            job = c.status(args.job_id)
            if not job.get("artifacts"):
                error = job.get("error") or {}
                why = f": {error.get('detail') or error.get('title')}" if error else ""
                print(
                    f"gsa: error: job {args.job_id} is {job.get('state')}{why}; it has no results to fetch",
                    file=sys.stderr,
                )
                return 1
        for p in c.fetch_all(args.job_id, args.out, args.names or None):
            print(p)
    return 0


def main(argv=None) -> int:
    """Stand-alone entry (python -m service.cli ...) until gsa/cli.py wires these verbs."""
    parser = argparse.ArgumentParser(prog="gsa")
    add_service_parsers(parser.add_subparsers(dest="cmd", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
