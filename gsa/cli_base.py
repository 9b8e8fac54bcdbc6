"""What every `gsa` verb shares: the one-line error, exit codes, lazy argparse choices, the
progress printer, the format names."""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from collections.abc import Sequence

from gsa.errors import GSAError

EXIT_FAILED = 1
# gsa.io.formats.FORMATS, spelled out so building the parser imports nothing (a test checks they agree)
FORMAT_CHOICES = ("ply", "compressed-ply", "splat", "ksplat", "spz", "sog", "glb")


class VectorArgumentParser(argparse.ArgumentParser):
    """argparse reads a value that starts with "-" as an option unless it is one plain negative
    number, so `--up -0.1,0.99,0:0,1,0` failed with "expected one argument". Here any value made
    of a minus sign, digits, points, exponents, commas and colons is a value (no gsa option looks
    like that). Sub-commands' parsers are of this class too (add_subparsers uses the parent's)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-\.?\d[\d.eE+\-,:;]*$")


class CliError(GSAError):
    """An error to show as one line."""


class _LazyChoices(Sequence):
    """argparse `choices` read from a module on first use (validation, help), so that
    building the parser does not import it (gsa.synth for `gsa align`)."""

    def __init__(self, module: str, name: str):
        self.module, self.name = module, name
        self._values: tuple | None = None

    def _load(self) -> tuple:
        if self._values is None:
            self._values = tuple(getattr(importlib.import_module(self.module), self.name))
        return self._values

    def __getitem__(self, index):
        return self._load()[index]

    def __len__(self) -> int:
        return len(self._load())

    def __repr__(self) -> str:
        return repr(self._load())


def lazy_choices(action: argparse.Action, module: str, name: str) -> None:
    """Set after add_argument, which formats (so iterates) any choices it is given."""
    action.choices = _LazyChoices(module, name)


class ProgressPrinter:
    """Stage and percentage on stderr: rewritten in place on a terminal, a line
    per stage change (and per 25%) otherwise so logs stay short."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.last: tuple[str, int] | None = None

    def __call__(self, stage: str, fraction: float) -> None:
        if not self.enabled:
            return
        pct = int(fraction * 100)
        if self.tty:
            sys.stderr.write(f"\r{stage:<12} {pct:3d}%")
            if stage == "done":
                sys.stderr.write("\n")
            sys.stderr.flush()
            return
        bucket = pct // 25
        if self.last is None or self.last[0] != stage or self.last[1] != bucket:
            print(f"[gsa] {stage} {pct}%", file=sys.stderr, flush=True)
            self.last = (stage, bucket)
