"""Instances kept out of training so they stay fair evaluation shapes.

Every tool that turns the manifest into training data calls `refuse_heldout` first: a held-out
mesh that slipped into the manifest must stop the run, not be silently trained on.
"""

import re

HELDOUT_SHAPENET = frozenset(
    {
        "4de5861211ad5b95e7ef9fff09638f8e",
        "4de653411d132abdf1e2558bb9cfc329",
        "4dfe2199fdd333d09837a3d08a6a1966",
        "4e2769ec84c0bd0454eefcdc602d4520",
        "4e4ae13865bf47f41adbb4c4e06ad649",
        "50c0de8fb13d6421dbbc9440457e303e",
        "50cdaa9e33fc853ecb2a965e75be701c",
        "50db85e4889831dff155d75bbf62b80",
        "51c60589bdd1ed73d4d8765e3910f617",
        "a047cb14c22517e6f33e284fed03c3fc",
        "341a2d3df9800314fa260f4362cac599",
        "341c9b0583d31770492d9da2668ec34c",
        "341e18eafb46f892a6fee8e2140acec9",
        "341e24df542e0676d42b9650f19dd425",
        "341fcdd8a40a2612456cbf78e1e89022",
        "1ea9ea99ac8ed233bf355ac8109b9988",
        "1eaf8db2dd2b710c7d5b1b70ae595e60",
        "1f035aa5fc6da0983ecac81e09b15ea9",
        "3a7439cfaa9af51faf1af397e14a566d",
        "3c0467f96e26b8c6a93445a1757adf6",
        "2d204f50f33b3994fe52ffd0e748a1ab",
        "4438e29f9d3cf45bfe52ffd0e748a1ab",
        "497833f2073ba6ff70d45c28bef72613",
        "56e194146b9e584b3321831d2245cf06",
        "7b5b032a2cddeebc54d7082b34825ef0",
    }
)
HELDOUT_CAPOD = frozenset({"m169", "m170", "m171", "m172", "m173"})
HELDOUT = HELDOUT_SHAPENET | HELDOUT_CAPOD


def refuse_heldout(entries):
    """Raise ValueError naming every held-out instance among `entries` (manifest dicts)."""
    # the path is checked too, so an entry with a mistyped instance id is still caught
    names = set()
    for e in entries:
        names.add(str(e.get("instance")))
        names.update(re.split(r"[/.]", str(e.get("path", ""))))
    bad = sorted(names & HELDOUT)
    if bad:
        raise ValueError(f"held-out instances must not be used for training: {', '.join(bad)}")
