"""The import direction analysis <- calibration <- daq <- pipelines, and analysis stays pure."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ["analysis", "calibration", "daq", "pipelines"]
ALLOWED = {layer: set(LAYERS[: i + 1]) for i, layer in enumerate(LAYERS)}
PURE_THIRD_PARTY = {"numpy", "scipy"}


def _imports(path: Path, layer: str) -> list[tuple[int, str]]:
    """(line, absolute module) for every import in ``path`` (relative ones resolved)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    rel_parts = ["cdpr", layer, *path.relative_to(ROOT / layer).with_suffix("").parts]
    package = rel_parts[:-1] if path.name != "__init__.py" else rel_parts[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append((node.lineno, mod))
    return out


def _py_files(layer: str) -> list[Path]:
    return sorted((ROOT / layer).rglob("*.py"))


@pytest.mark.parametrize("layer", LAYERS)
def test_imports_point_one_way(layer: str) -> None:
    bad = []
    for path in _py_files(layer):
        for line, mod in _imports(path, layer):
            parts = mod.split(".")
            if parts[0] == "cdpr" and len(parts) > 1 and parts[1] not in ALLOWED[layer]:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, (
        "imports against the direction analysis <- calibration <- daq <- pipelines:\n"
        + "\n".join(bad)
    )


def test_analysis_is_pure() -> None:
    stdlib = set(sys.stdlib_module_names)
    forbidden_stdlib = {
        "os",
        "io",
        "socket",
        "subprocess",
        "threading",
        "pathlib",
        "shutil",
        "tempfile",
    }
    bad = []
    for path in _py_files("analysis"):
        for line, mod in _imports(path, "analysis"):
            top = mod.split(".")[0]
            if top in ("cdpr", "__future__"):
                continue
            if top in forbidden_stdlib or (top not in stdlib and top not in PURE_THIRD_PARTY):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, "analysis/ must stay pure (numpy/scipy and pure stdlib only):\n" + "\n".join(
        bad
    )


def test_checker_sees_a_violation(tmp_path: Path) -> None:
    """The checker itself: a relative import two levels up from analysis is resolved and caught."""
    f = ROOT / "analysis" / "_probe_for_test.py"
    try:
        f.write_text("from ..daq import source\n")
        mods = [m for _, m in _imports(f, "analysis")]
    finally:
        f.unlink()
    assert mods == ["cdpr.daq"]
