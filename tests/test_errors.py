"""Every exception class of gsa/ derives from the library's base, gsa.errors.GSAError.

Read with `ast` (nothing imported: gsa.recon needs OpenCV), so a new error kind that forgets
the base fails here rather than printing a traceback from the `gsa` command.
"""

from __future__ import annotations

import ast
import builtins
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BUILTIN_EXCEPTIONS = {
    name for name, value in vars(builtins).items() if isinstance(value, type) and issubclass(value, BaseException)
}
BUILTIN_WARNINGS = {name for name in BUILTIN_EXCEPTIONS if issubclass(getattr(builtins, name), Warning)}


def _base_name(node: ast.expr) -> str:
    return node.attr if isinstance(node, ast.Attribute) else getattr(node, "id", "")


def _classes() -> dict[str, tuple[str, list[str]]]:
    """Class name -> (where, base names) for every top-level class in gsa/."""
    out = {}
    for path in sorted((ROOT / "gsa").rglob("*.py")):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.ClassDef):
                out[node.name] = (f"{path.relative_to(ROOT)}:{node.lineno}", [_base_name(b) for b in node.bases])
    return out


def _ancestors(name: str, classes: dict) -> set[str]:
    seen, todo = set(), [name]
    while todo:
        for base in classes.get(todo.pop(), ("", []))[1]:
            if base not in seen:
                seen.add(base)
                todo.append(base)
    return seen


def test_every_error_of_the_library_derives_from_gsa_error():
    classes = _classes()
    errors = {
        name: where
        for name, (where, _) in classes.items()
        if name != "GSAError" or "errors.py" not in where
        if _ancestors(name, classes) & BUILTIN_EXCEPTIONS and not _ancestors(name, classes) & BUILTIN_WARNINGS
    }
    assert {"PlyError", "SfMError", "CliError", "ServiceError"} <= set(errors)
    missing = sorted(
        f"{name} ({where})" for name, where in errors.items() if "GSAError" not in _ancestors(name, classes)
    )
    assert not missing, "errors not derived from gsa.errors.GSAError: " + ", ".join(missing)


def test_the_kinds_keep_their_builtin_bases():
    from gsa.errors import GSAError
    from gsa.io.formats import FormatError
    from gsa.io.ply import PlyError
    from gsa.model import ModelError
    from gsa.sim3 import DegenerateCorrespondencesError
    from gsa.ziparchive import ZipArchiveError

    for kind in (FormatError, PlyError, ModelError, DegenerateCorrespondencesError, ZipArchiveError):
        assert issubclass(kind, GSAError) and issubclass(kind, ValueError), kind
