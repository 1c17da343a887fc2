"""Imports run one way: nodes and tools use the core, never the reverse, and the core's stages
import only the stages before them, in the order the README's Layout section states once."""

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "terrain_nav_ros"


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Every terrain_nav_ros module ``path`` imports (relative ones resolved), at any depth."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = ".".join(base[:len(base) - node.level + 1])
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            found.add(module)
            # ``from package import submodule`` imports the submodule
            found.update(f"{module}.{a.name}" for a in node.names
                         if (REPO.joinpath(*module.split("."), f"{a.name}.py")).is_file())
    return {m for m in found if m.split(".")[0] == "terrain_nav_ros"}


def _modules(folder: Path):
    return {_module_name(p): _imports(p) for p in sorted(folder.rglob("*.py"))}


def stage_order() -> list[str]:
    """The core's stages, upstream first, from the README's Layout section."""
    text = (REPO / "README.md").read_text()
    layout = text.split("## Layout", 1)[1].split("\n## ", 1)[0]
    line = next(line for line in layout.splitlines() if line.startswith("Stage order"))
    return re.findall(r"`(\w+)`", line)


def test_the_core_imports_no_node_or_tool():
    for module, imported in _modules(PACKAGE / "core").items():
        bad = {m for m in imported
               if m.startswith(("terrain_nav_ros.nodes", "terrain_nav_ros.tools"))}
        assert not bad, f"{module} imports {sorted(bad)}"


def test_tools_start_nodes_by_name_and_never_import_them():
    for module, imported in _modules(PACKAGE / "tools").items():
        bad = {m for m in imported if m.startswith("terrain_nav_ros.nodes")}
        assert not bad, f"{module} imports {sorted(bad)}"


def test_every_stage_is_in_the_readmes_order_and_nothing_else_is_a_stage():
    stages = stage_order()
    on_disk = {p.parent.name for p in (PACKAGE / "core").glob("*/__init__.py")}
    assert len(stages) == len(set(stages)) and set(stages) == on_disk, (stages, on_disk)


def test_stages_import_only_the_stages_before_them():
    stages = stage_order()
    for module, imported in _modules(PACKAGE / "core").items():
        parts = module.split(".")
        if len(parts) < 4:
            continue   # core's own shared helpers (_numba): they import no stage
        own = stages.index(parts[2])
        for target in imported:
            target_parts = target.split(".")
            if len(target_parts) < 3 or target_parts[1] != "core" \
                    or target_parts[2] not in stages:
                continue
            assert stages.index(target_parts[2]) <= own, (
                f"{module} imports {target}: stage {target_parts[2]!r} comes after "
                f"{parts[2]!r} in the README's stage order {stages}")


def test_the_checker_sees_relative_imports():
    imported = _imports(PACKAGE / "core" / "matching" / "pva_fix.py")
    assert "terrain_nav_ros.core.terrain.georef" in imported
