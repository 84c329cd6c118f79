"""The packages of `sim_harness` import only downwards (sim < dataset < learning < experiments <
hil), and `companion` never imports the simulation side: the walls of ARCHITECTURE.md."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LAYERS = ("sim", "dataset", "learning", "experiments", "hil")
SHARED = {"errors"}  # below every package


def _imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
    return names


def _package_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "sim_harness" else None


@pytest.mark.parametrize("layer", LAYERS)
def test_a_package_imports_only_itself_and_what_lies_below(layer: str) -> None:
    allowed = {*LAYERS[: LAYERS.index(layer) + 1], *SHARED}
    offences = []
    for path in sorted((ROOT / "sim_harness" / layer).rglob("*.py")):
        for module in _imports(path):
            package = _package_of(module)
            if package is not None and package not in allowed and package in {*LAYERS, "cli"}:
                offences.append(f"{path.relative_to(ROOT)} imports {module}")
    assert not offences, "\n".join(offences)


def test_companion_never_imports_the_simulation_side() -> None:
    banned = ("sim_harness", "pybullet", "matplotlib", "pymavlink")
    offences = [
        f"{path.relative_to(ROOT)} imports {module}"
        for path in sorted((ROOT / "companion").rglob("*.py"))
        for module in _imports(path)
        if module.split(".")[0] in banned
    ]
    assert not offences, "\n".join(offences)


def test_the_top_level_holds_only_the_cli_and_the_shared_errors() -> None:
    modules = {p.stem for p in (ROOT / "sim_harness").glob("*.py")}
    assert modules == {"__init__", "cli", "errors"}
