"""Convert the manifest's public meshes into normalised .npz files in one canonical frame.

    python -m training.fetch_meshes --out DIR [--mirror-root /work/.mirror]

Each mesh is read from a local git mirror when there is one, else from a blobless clone;
rotated by its frame's `to_canonical` (+Y up, +Z front, see manifest.json); bbox-centred and
scaled to a unit bbox diagonal; written as DIR/<category>/<source-short>_<instance>.npz with
V float32 (n,3), F int32 (m,3), C float16 (m,3) per-face RGB (NaN where the mesh has none),
the layout of shared/data/category-dev.
"""

import argparse
import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from training.heldout import refuse_heldout

MANIFEST = Path(__file__).with_name("manifest.json")
CACHE = Path.home() / ".cache" / "gsa-training" / "repos"
# file-name prefixes: short, and distinct per source so instances never collide
SHORT = {
    "ajhamdi/semantic-robustness": "shapenet",
    "trneedham/QuantizedGromovWasserstein": "capod",
    "category-dev": "catdev",
}


def parse_mtl(text):
    """Material name -> Kd diffuse RGB."""
    kd, name = {}, None
    for line in text.splitlines():
        tok = line.split()
        if len(tok) >= 2 and tok[0] == "newmtl":
            name = " ".join(tok[1:])
        elif len(tok) >= 4 and tok[0] == "Kd" and name is not None:
            kd[name] = [float(t) for t in tok[1:4]]
    return kd


def parse_obj(text, read_mtl=None):
    """Parse OBJ text into (V float32 (n,3), F int32 (m,3), C float16 (m,3)).

    Faces may use v, v/vt, v/vt/vn or v//vn and negative (relative) indices; polygons are
    fan-triangulated. `read_mtl(name)` returns an .mtl file's text (or None): its Kd colours
    become per-face RGB via usemtl; faces without a known material get NaN.
    """
    verts, faces, colours = [], [], []
    kd, colour = {}, [np.nan] * 3
    for line in text.splitlines():
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "v":
            verts.append([float(t) for t in tok[1:4]])
        elif tok[0] == "f":
            # a negative index counts back from the vertices read so far
            idx = [int(t.split("/")[0]) for t in tok[1:]]
            idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
            if min(idx) < 0 or max(idx) >= len(verts):
                raise ValueError(f"face index out of range: {line.strip()}")
            for k in range(1, len(idx) - 1):
                faces.append([idx[0], idx[k], idx[k + 1]])
                colours.append(colour)
        elif tok[0] == "mtllib" and read_mtl is not None:
            mtl = read_mtl(" ".join(tok[1:]))
            if mtl is not None:
                kd.update(parse_mtl(mtl))
        elif tok[0] == "usemtl":
            colour = kd.get(" ".join(tok[1:]), [np.nan] * 3)
    if not verts or not faces:
        raise ValueError("no vertices or no faces")
    return (
        np.asarray(verts, np.float32).reshape(-1, 3),
        np.asarray(faces, np.int32).reshape(-1, 3),
        np.asarray(colours, np.float16).reshape(-1, 3),
    )


def normalise(V, to_canonical):
    """Rotate into the canonical frame, centre the bbox, scale its diagonal to 1."""
    V = V.astype(np.float64) @ np.asarray(to_canonical, np.float64).T
    lo, hi = V.min(0), V.max(0)
    return ((V - (lo + hi) / 2) / np.linalg.norm(hi - lo)).astype(np.float32)


class RepoReader:
    """Reads files at a commit: from <mirror-root>/<owner>+<name>/repo[/.git] when present,
    else from a blobless clone in CACHE (git fetches each blob on first `git show`, so only
    the meshes used are downloaded, not a whole checkout of images)."""

    def __init__(self, mirror_root):
        self.mirror_root = Path(mirror_root)
        self.gitdirs = {}

    def gitdir(self, repo):
        if repo not in self.gitdirs:
            base = self.mirror_root / repo.replace("/", "+") / "repo"
            for d in (base / ".git", base):
                if (d / "HEAD").is_file():
                    self.gitdirs[repo] = d
                    break
            else:
                clone = CACHE / repo.replace("/", "+")
                if not (clone / ".git").is_dir():
                    clone.parent.mkdir(parents=True, exist_ok=True)
                    url = f"https://github.com/{repo}"
                    subprocess.run(["git", "clone", "--filter=blob:none", "--no-checkout", url, str(clone)], check=True)
                self.gitdirs[repo] = clone / ".git"
        return self.gitdirs[repo]

    def read(self, repo, commit, path):
        """File text at commit:path, or None when it is absent (missing blob, no such path)."""
        r = subprocess.run(
            ["git", "--git-dir", str(self.gitdir(repo)), "show", f"{commit}:{path}"], capture_output=True
        )
        return r.stdout.decode("utf-8", "replace") if r.returncode == 0 else None


def load_entry(entry, reader, dev_root):
    """(V, F, C) of one manifest entry in its source's own coordinates."""
    if entry["source"] == "category-dev":
        with np.load(Path(dev_root) / entry["path"]) as z:
            return z["V"], z["F"], z["C"]
    text = reader.read(entry["source"], entry["commit"], entry["path"])
    if text is None:
        raise ValueError("file not readable from git (blob absent?)")
    folder = str(Path(entry["path"]).parent)
    return parse_obj(text, lambda name: reader.read(entry["source"], entry["commit"], f"{folder}/{name}"))


def frame_of(manifest, entry):
    """to_canonical: the entry's own override, else its (source, source class) frame."""
    if "to_canonical" in entry:
        return entry["to_canonical"]
    return manifest["frames"][entry["source"]][entry["source_class"]]["to_canonical"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--mirror-root", default="/work/.mirror")
    ap.add_argument("--dev-root", default="/work/shared/data/category-dev", help="category-dev .npz folder")
    ap.add_argument("--manifest", default=MANIFEST, type=Path)
    args = ap.parse_args(argv)

    manifest = json.loads(args.manifest.read_text())
    entries = [e for e in manifest["entries"] if "dropped" not in e]
    refuse_heldout(entries)  # before anything is read or written
    reader = RepoReader(args.mirror_root)
    index, counts = [], Counter()
    for e in entries:
        try:
            V, F, C = load_entry(e, reader, args.dev_root)
        except (ValueError, OSError, KeyError) as err:
            print(f"skip {e['source']}:{e['path']}: {err}", file=sys.stderr)
            continue
        rel = f"{e['category']}/{SHORT[e['source']]}_{e['instance']}.npz"
        (args.out / e["category"]).mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.out / rel, V=normalise(V, frame_of(manifest, e)), F=F, C=C)
        index.append({"category": e["category"], "file": rel, "dev_instance": e.get("dev_instance")})
        counts[e["category"]] += 1
    (args.out / "index.json").write_text(json.dumps(index, indent=1) + "\n")
    for cat in sorted(counts):
        print(f"{cat:10s} {counts[cat]}")
    print(f"total      {sum(counts.values())}")


if __name__ == "__main__":
    main()
