"""Put the public real captures of benchmarks/captures_manifest.json into a folder for `gsa bench real`.

    python -m benchmarks.fetch_captures --out /work/train-data/captures [--git-dir DIR ...]

Each capture is a git blob of a public GitHub repository at a stated commit (the manifest gives
repository, commit, path, sha256, Gaussian count, format, licence where one is stated). The
captures stay out of this repository: this script takes them from a local clone of each source
repository and checks every byte against the manifest's sha256.

Where the clones come from: `--git-dir OWNER/NAME=PATH` names one (a bare or ordinary clone:
`git clone --filter=blob:none https://github.com/OWNER/NAME` will do, git fetches the blobs asked
for). Without it, ./.mirror/OWNER+NAME/repo and /work/.mirror/OWNER+NAME/repo are tried (where
the session's fetch tool stores a repository snapshot, which is how the files were first got).

Files already in --out whose sha256 matches are kept; a file whose sha256 does not match is
refused (ChecksumError), never overwritten silently: delete it and run again. `--verify` only
checks the files already in --out.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
from pathlib import Path

MANIFEST = Path(__file__).with_name("captures_manifest.json")
MIRROR_ROOTS = (Path(".mirror"), Path("/work/.mirror"))


class ChecksumError(ValueError):
    """A capture's bytes do not match the manifest's sha256."""


def load_manifest(path: str | Path = MANIFEST) -> list[dict]:
    entries = json.loads(Path(path).read_text())["captures"]
    for e in entries:
        missing = {"file", "repo", "commit", "path", "sha256"} - set(e)
        if missing:
            raise ValueError(f"{path}: entry {e.get('file', '?')} lacks {', '.join(sorted(missing))}")
    return entries


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def check(entry: dict, data: bytes, where: str) -> bytes:
    """`data` if its sha256 is the manifest's, else ChecksumError."""
    got = sha256(data)
    if got != entry["sha256"]:
        raise ChecksumError(
            f"{where}: sha256 {got} is not the manifest's {entry['sha256']} for {entry['file']} "
            f"({entry['repo']} @ {entry['commit'][:12]}:{entry['path']}); not used"
        )
    return data


def verify_folder(out: str | Path, entries: list[dict]) -> dict[str, str]:
    """Each entry's state in `out`: 'ok' or 'missing'; ChecksumError on a file that differs."""
    states = {}
    for e in entries:
        f = Path(out) / e["file"]
        if not f.is_file():
            states[e["file"]] = "missing"
            continue
        check(e, f.read_bytes(), str(f))
        states[e["file"]] = "ok"
    return states


def find_git_dir(repo: str, given: dict[str, Path]) -> Path | None:
    if repo in given:
        return given[repo]
    for root in MIRROR_ROOTS:
        d = root / repo.replace("/", "+") / "repo"
        if d.is_dir():
            return d
    return None


def read_blob(git_dir: Path, commit: str, path: str) -> bytes:
    proc = subprocess.run(
        ["git", f"--git-dir={git_dir}", "cat-file", "blob", f"{commit}:{path}"], capture_output=True, check=False
    )
    if proc.returncode != 0:
        raise FileNotFoundError(f"{git_dir}: no {commit[:12]}:{path} ({proc.stderr.decode(errors='replace').strip()})")
    return proc.stdout


def fetch(out: str | Path, entries: list[dict], git_dirs: dict[str, Path]) -> dict[str, str]:
    """Write each missing capture into `out` from its repository's clone; returns each file's state
    ('ok' kept, 'written', or why it was not got). A mismatching file raises ChecksumError."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    states = verify_folder(out, entries)
    for e in entries:
        if states[e["file"]] == "ok":
            continue
        git_dir = find_git_dir(e["repo"], git_dirs)
        if git_dir is None:
            states[e["file"]] = f"no clone of {e['repo']} (give --git-dir {e['repo']}=PATH)"
            continue
        try:
            blob = read_blob(git_dir, e["commit"], e["path"])
        except FileNotFoundError as exc:  # no such clone, commit or path (or a partial clone offline)
            states[e["file"]] = str(exc)
            continue
        data = check(e, blob, f"{git_dir}:{e['path']}")
        tmp = out / (e["file"] + ".part")
        tmp.write_bytes(data)
        tmp.replace(out / e["file"])
        states[e["file"]] = "written"
    return states


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="folder for the captures (outside the repository)")
    p.add_argument("--manifest", default=str(MANIFEST))
    p.add_argument(
        "--git-dir", action="append", default=[], metavar="OWNER/NAME=PATH", help="a clone of a source repository"
    )
    p.add_argument("--verify", action="store_true", help="only check the files already in --out")
    args = p.parse_args(argv)
    git_dirs = {}
    for item in args.git_dir:
        repo, sep, path = item.partition("=")
        if not sep:
            p.error(f"--git-dir {item!r}: give OWNER/NAME=PATH")
        git_dirs[repo] = Path(path)
    entries = load_manifest(args.manifest)
    try:
        states = verify_folder(args.out, entries) if args.verify else fetch(args.out, entries, git_dirs)
    except ChecksumError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    for name, state in states.items():
        print(f"{name}: {state}")
    bad = [n for n, s in states.items() if s not in ("ok", "written")]
    print(f"{len(states) - len(bad)}/{len(states)} captures in {args.out}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
