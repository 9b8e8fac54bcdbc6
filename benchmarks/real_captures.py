"""`gsa bench real --data DIR`: split pairs from a folder of REAL 3DGS captures.

Every capture the folder holds (any format gsa.io reads, sniffed from the bytes) gives
PAIRS_PER_CAPTURE pairs. For each pair its Gaussians are dealt at random into two disjoint
halves (no Gaussian in both), each half is cut by its own random plane (60–90 % kept), and the
target half is moved by a random Sim(3) (≤ 180° per axis, 0.1–10× scale). What a real capture
brings is kept as exported: SH degree, floaters, ground, quantised positions, alpha = 1.

Two variants, one table each: as captured, and with the source under another exposure and
white balance (±1 stop, gsa.synth.shift_exposure), as a second capture on another day would
record it. Success: RRE < 5° (strict: a real capture has no known symmetry).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np

from benchmarks.records import Pair
from gsa.io.formats import EXTENSIONS, format_for_path, read_model
from gsa.synth.perturb import random_sim3
from gsa.synth.variants import cut_by_plane, random_exposure, shift_exposure

PAIRS_PER_CAPTURE = (8, 2)  # full, --quick
KEEP = (0.6, 0.9)
# --quick draws each half from at most this many Gaussians of the capture.
QUICK_GAUSSIANS = 40_000


def find_captures(folder: str | Path) -> list[Path]:
    """The 3DGS files of a folder (by extension; the reader sniffs the bytes), sorted."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder")
    return sorted(p for p in folder.iterdir() if p.is_file() and format_for_path(p) in EXTENSIONS)


@cache
def _load(path: Path):
    return read_model(path)


def split_pair(model, rng: np.random.Generator, keep: tuple[float, float] = KEEP):
    """Two disjoint halves of `model` (each Gaussian dealt to one at random), each cut by
    its own random plane keeping a share in `keep`."""
    to_source = rng.random(len(model)) < 0.5
    source = cut_by_plane(model.subset(to_source), rng, keep)
    target = cut_by_plane(model.subset(~to_source), rng, keep)
    return source, target


def real_split_pairs(data: str | Path, quick: bool, seed: int, exposure: bool = False) -> list[Pair]:
    """PAIRS_PER_CAPTURE split pairs per capture of `data`; labels '<file stem>-<k>'."""
    captures = find_captures(data)
    if not captures:
        raise ValueError(f"{data}: no 3DGS files found ({', '.join(sorted(set(EXTENSIONS.values())))})")
    per_capture = PAIRS_PER_CAPTURE[1] if quick else PAIRS_PER_CAPTURE[0]
    pairs: list[Pair] = []
    for c, path in enumerate(captures):
        for k in range(per_capture):

            def make(c=c, k=k, path=path):
                rng = np.random.default_rng([seed, 26, c, k])
                model = _load(path)
                if quick and len(model) > QUICK_GAUSSIANS:
                    model = model.subset(np.sort(rng.choice(len(model), QUICK_GAUSSIANS, replace=False)))
                source, target = split_pair(model, rng)
                truth = random_sim3(rng)
                if exposure:
                    source = shift_exposure(source, random_exposure(rng))
                return source, target.transformed(truth), truth

            pairs.append((f"{path.name}-{k}", make))
    return pairs


def capture_of(label: str) -> dict:
    return {"category": label.rsplit("-", 1)[0]}
