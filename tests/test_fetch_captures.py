"""benchmarks.fetch_captures: captures are taken from a git clone at the manifest's commit and
checked byte for byte against its sha256; a file that differs is refused, never used. No network."""

import hashlib
import json
import subprocess

import pytest

from benchmarks import fetch_captures as fc


@pytest.fixture
def source(tmp_path):
    """A git repository with one 'capture' committed, and a manifest naming it."""
    work = tmp_path / "src"
    work.mkdir()
    data = b"not really a splat, but bytes all the same" * 10
    (work / "assets").mkdir()
    (work / "assets" / "thing.splat").write_bytes(data)
    git = ["git", "-C", str(work), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git[:3], "init", "-q"], check=True)
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "add"], check=True)
    commit = subprocess.run([*git, "rev-parse", "HEAD"], check=True, capture_output=True, text=True).stdout.strip()
    entry = {
        "file": "thing.splat",
        "repo": "someone/things",
        "commit": commit,
        "path": "assets/thing.splat",
        "sha256": hashlib.sha256(data).hexdigest(),
    }
    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps({"captures": [entry]}))
    return {"git_dir": work / ".git", "manifest": manifest, "data": data, "entry": entry}


def test_fetch_writes_a_checked_capture_and_keeps_it(source, tmp_path):
    entries = fc.load_manifest(source["manifest"])
    out = tmp_path / "out"
    assert fc.fetch(out, entries, {"someone/things": source["git_dir"]}) == {"thing.splat": "written"}
    assert (out / "thing.splat").read_bytes() == source["data"]
    assert fc.fetch(out, entries, {}) == {"thing.splat": "ok"}  # no clone needed for a file already right
    assert fc.verify_folder(out, entries) == {"thing.splat": "ok"}


def test_a_sha_mismatch_is_refused(source, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "thing.splat").write_bytes(b"something else")
    entries = fc.load_manifest(source["manifest"])
    with pytest.raises(fc.ChecksumError, match="is not the manifest's"):
        fc.verify_folder(out, entries)
    with pytest.raises(fc.ChecksumError):
        fc.fetch(out, entries, {"someone/things": source["git_dir"]})
    assert (out / "thing.splat").read_bytes() == b"something else"  # not overwritten
    assert fc.main(["--out", str(out), "--manifest", str(source["manifest"]), "--verify"]) == 1


def test_a_source_blob_that_differs_from_the_manifest_is_not_written(source, tmp_path):
    bad = dict(source["entry"], sha256="0" * 64)
    manifest = tmp_path / "bad.json"
    manifest.write_text(json.dumps({"captures": [bad]}))
    out = tmp_path / "out"
    with pytest.raises(fc.ChecksumError, match="not used"):
        fc.fetch(out, fc.load_manifest(manifest), {"someone/things": source["git_dir"]})
    assert not (out / "thing.splat").exists()


def test_missing_clone_and_incomplete_entries_are_reported(source, tmp_path):
    states = fc.fetch(tmp_path / "out", fc.load_manifest(source["manifest"]), {"someone/things": tmp_path / "nowhere"})
    assert "nowhere" in states["thing.splat"] and not (tmp_path / "out" / "thing.splat").exists()
    manifest = tmp_path / "partial.json"
    manifest.write_text(json.dumps({"captures": [{"file": "x.splat", "repo": "a/b"}]}))
    with pytest.raises(ValueError, match="lacks commit, path, sha256"):
        fc.load_manifest(manifest)


def test_the_project_manifest_is_complete():
    entries = fc.load_manifest()
    assert len({e["file"] for e in entries}) == len(entries) >= 6
    assert all(len(e["sha256"]) == 64 and len(e["commit"]) == 40 and e["gaussians"] >= 20_000 for e in entries)
