"""docs/service.md states settings' defaults as `NAME` (default, …); each one that is a plain
number or true/false must be the default in service/settings.py (the docs said
GSA_MAX_MANY_MODELS 32 when the code had been 64 for a week)."""

from __future__ import annotations

import re

from service.settings import Settings
from tests.service.conftest import ROOT

DOC = ROOT / "docs" / "service.md"


def _documented() -> list[tuple[str, str]]:
    """(field, default) for every `GSA_NAME` (default…) or `NAME` (default…) in the docs' settings
    list and in its tables (elsewhere a parenthesis after a name is often an answer: "(422, …)")."""
    text = DOC.read_text()
    settings = text[text.index("## Settings (environment") :]
    settings = settings[: settings.index("\n## ", 4)]
    tables = "\n".join(line for line in text.splitlines() if line.startswith("|"))
    found = []
    for m in re.finditer(r"`(?:GSA_)?([A-Z][A-Z0-9_]+)` \(([^)]*)\)", settings + "\n" + tables):
        found.append((m.group(1).lower(), re.split(r"[,;]", m.group(2), maxsplit=1)[0].strip()))
    return found


def test_documented_defaults_are_the_code_defaults():
    fields = Settings.model_fields  # the declared defaults, whatever this process's GSA_* say
    checked, wrong = [], []
    for name, said in _documented():
        if name not in fields:
            continue
        value = fields[name].default
        if said in ("true", "false"):
            doc_value = said == "true"
        elif re.fullmatch(r"-?\d+(\.\d+)?", said):
            doc_value = float(said)
        else:
            continue  # a unit ("1 MiB", "5M"), a sentence, a host: not a plain number
        checked.append(name)
        if isinstance(value, bool) or isinstance(doc_value, bool):
            ok = value is doc_value
        else:
            ok = isinstance(value, int | float) and float(value) == doc_value
        if not ok:
            wrong.append((name, said, value))
    assert not wrong, f"docs/service.md says (name, docs, code): {wrong}"
    assert {"max_many_models", "max_sources", "max_attempts", "lease_s", "worker_memory_mb"} <= set(checked), checked
