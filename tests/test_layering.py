"""The package's floors: a module imports only from its own floor or the ones below (lazy imports too)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mewa_bench"
FLOORS = {"files": 0, "extras": 0, "game": 0, "design": 1, "envs": 2, "protocol": 3, "agents": 4}  # else: the edge
EDGE = 5
# (importer, imported): upward imports that are part of the design, each with its reason.
ALLOWED = {
    # SAPIEN mode: camera images are part of the observation, so the env builds the scene (lazily, only in that mode).
    ("mewa_bench.envs.mewa_env", "mewa_bench.render.scene"),
    # The offline baseline learns from a training dataset: reading one, with its checks (no test worker, no protocol
    # key), is the datasets package's (lazily, when training starts).
    ("mewa_bench.agents.dpt", "mewa_bench.datasets.training_data"),
    ("mewa_bench.agents.training_io", "mewa_bench.datasets.training_data"),  # an offline run's suite is its dataset's
    ("mewa_bench.agents.imitation", "mewa_bench.datasets.meta_episodes"),  # its whole meta-episodes
    ("mewa_bench.agents.ad", "mewa_bench.datasets.meta_episodes"),  # its learning histories, whole
}


def floor_of(module: str) -> int | None:
    """The floor of a mewa_bench module (None: not ours, or the package root, imported only for `__version__`)."""
    parts = module.split(".")
    if parts[0] != "mewa_bench" or len(parts) == 1:
        return None
    return FLOORS.get(parts[1], EDGE)


def imports_of(path: Path) -> set[str]:
    """Every module a file imports, at the top or inside functions."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return found


def module_name(path: Path) -> str:
    return module_name_in(path, PACKAGE)


def test_no_module_imports_from_a_higher_floor() -> None:
    upward = set()
    for path in sorted(PACKAGE.rglob("*.py")):
        importer = module_name(path)
        for imported in imports_of(path):
            low, high = floor_of(importer), floor_of(imported)
            if None not in (low, high) and high > low:
                upward.add((importer, imported))
    assert upward == ALLOWED


def test_the_floor_check_sees_lazy_imports(tmp_path: Path) -> None:
    source = tmp_path / "example.py"
    source.write_text("import numpy\n\ndef f():\n    from mewa_bench.leaderboard.build import build_leaderboards\n")
    assert imports_of(source) == {"numpy", "mewa_bench.leaderboard.build"}
    assert floor_of("mewa_bench.leaderboard.build") > floor_of("mewa_bench.design.exact") > floor_of("mewa_bench.game")


# Heavy libraries are imported lazily, inside the functions that need them: (code, what it must not load).
LIGHT = [
    ("import mewa_bench", ("torch", "lerobot", "sapien", "rerun", "mcap", "scipy", "ray")),
    ("import mewa_bench.datasets, mewa_bench.datasets.pack, mewa_bench.datasets.downloader",
     ("lerobot", "torch", "huggingface_hub", "datasets")),
    ("import mewa_bench.logs", ("mcap", "rerun", "PIL")),
    ("import mewa_bench.render", ("sapien",)),
    ("import mewa_bench.extras, mewa_bench.agents.rl2, mewa_bench.datasets.lerobot_recorder",
     ("torch", "lerobot", "datasets", "huggingface_hub")),
    ("import gymnasium as gym, mewa_bench; env = gym.make('mewa/MEWA-v0'); env.reset(seed=0); env.step(0)", ("sapien",)),
]


def loaded(code: str, modules: tuple[str, ...]) -> list[str]:
    """Which of `modules` a fresh interpreter has imported after running `code`."""
    import subprocess
    import sys

    probe = f"{code}\nimport sys\nprint(sorted({{m.split('.')[0] for m in sys.modules}} & {set(modules)!r}))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True, cwd=PACKAGE.parent)
    return eval(out.stdout.strip().splitlines()[-1])  # a printed list of names


@pytest.mark.parametrize("code, heavy", LIGHT)
def test_imports_stay_light(code: str, heavy: tuple[str, ...]) -> None:
    assert loaded(code, heavy) == []


def test_the_light_import_probe_sees_imports() -> None:
    assert loaded("import json, numpy", ("numpy", "scipy")) == ["numpy"]


def package_imports(path: Path, package: Path, modules: set[str], lazy: bool = False) -> set[str]:
    """The modules of `modules` that `path` imports when it is imported: its imports outside functions (those in
    classes, if, try and with blocks included; those under `if TYPE_CHECKING` left out), or with `lazy` all of them;
    relative ones resolved, and `from package import name` counted as the module package.name when there is one."""
    name = module_name_in(path, package)
    found: set[str] = set()

    def visit(statements: list[ast.stmt]) -> None:
        for node in statements:
            if isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = name.split(".")[:len(name.split(".")) - node.level + (path.name == "__init__.py")]
                    base = ".".join([*parts, *([base] if base else [])])
                found.update(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base
                             for alias in node.names)
            elif isinstance(node, ast.If) and "TYPE_CHECKING" not in ast.unparse(node.test):
                visit(node.body)
                visit(node.orelse)
            elif isinstance(node, ast.Try):
                for block in (node.body, *(handler.body for handler in node.handlers), node.orelse, node.finalbody):
                    visit(block)
            elif isinstance(node, (ast.With, ast.ClassDef)):
                visit(node.body)

    tree = ast.parse(path.read_text())
    if lazy:  # every import, wherever it is, but those for type checkers only (never run)
        for node in ast.walk(tree):
            if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
                node.body = []
        visit([node for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom))])
    else:
        visit(tree.body)
    return {module for module in found if module in modules and module != name}


def module_name_in(path: Path, package: Path) -> str:
    """The dotted name of the module at `path` in `package` (a package's own name for its __init__.py)."""
    return ".".join(path.relative_to(package.parent).with_suffix("").parts).removesuffix(".__init__")


def import_cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The import cycles of `graph` (module -> modules it imports): its strongly connected parts of two or more
    modules (Tarjan's algorithm)."""
    order: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[set[str]] = []

    def visit(module: str) -> None:
        order[module] = low[module] = len(order)
        stack.append(module)
        for imported in sorted(graph[module]):
            if imported not in order:
                visit(imported)
                low[module] = min(low[module], low[imported])
            elif imported in stack:
                low[module] = min(low[module], order[imported])
        if low[module] == order[module]:
            part = set()
            while not part or module not in part:
                part.add(stack.pop())
            if len(part) > 1:
                cycles.append(part)

    for module in sorted(graph):
        if module not in order:
            visit(module)
    return cycles


def import_graph(package: Path, lazy: bool = False) -> dict[str, set[str]]:
    """Which of the package's modules each of them imports: at module level, or with `lazy` anywhere."""
    paths = {module_name_in(path, package): path for path in sorted(package.rglob("*.py"))}
    return {module: package_imports(path, package, set(paths), lazy) for module, path in paths.items()}


def test_no_module_imports_another_in_a_cycle() -> None:
    assert import_cycles(import_graph(PACKAGE)) == []


# Lazy imports (inside functions) run late enough not to fail, but a circle is still two rooms that need each other.
KNOWN_LAZY_CYCLES: list[set[str]] = []


def test_no_import_cycle_through_lazy_imports_either_but_the_known_one() -> None:
    assert [cycle for cycle in import_cycles(import_graph(PACKAGE, lazy=True)) if cycle not in KNOWN_LAZY_CYCLES] == []


def test_the_cycle_check_sees_cycles(tmp_path: Path) -> None:
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from pkg.sub import b\n")
    (package / "sub" / "__init__.py").write_text("")
    (package / "sub" / "b.py").write_text("from ..c import value\n")
    (package / "c.py").write_text("try:\n    import pkg.a\nexcept ImportError:\n    pass\nvalue = 1\n")
    (package / "d.py").write_text("import pkg.c\n\ndef f():\n    from pkg import d\n")
    (package / "e.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg import a\n")
    assert import_cycles(import_graph(package)) == [{"pkg.a", "pkg.sub.b", "pkg.c"}]
    (package / "c.py").write_text("value = 1\n")
    assert import_cycles(import_graph(package)) == []
    (package / "c.py").write_text("value = 1\n\ndef f():\n    import pkg.d\n")
    assert import_cycles(import_graph(package)) == []
    assert import_cycles(import_graph(package, lazy=True)) == [{"pkg.c", "pkg.d"}]
    (package / "a.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg import e\n")
    assert import_cycles(import_graph(package, lazy=True)) == [{"pkg.c", "pkg.d"}]  # a type checker's import: no cycle


MAX_LINES = 500
LONG_FILE_REASON = "longer than 500 lines because"


def long_files_without_a_reason(package: Path) -> list[str]:
    """The package's files above MAX_LINES lines whose opening docstring has no line saying why."""
    unexplained = []
    for path in sorted(package.rglob("*.py")):
        text = path.read_text()
        if len(text.splitlines()) > MAX_LINES and LONG_FILE_REASON not in (ast.get_docstring(ast.parse(text)) or ""):
            unexplained.append(f"{path.relative_to(package.parent)}: {len(text.splitlines())} lines")
    return unexplained


def test_no_file_is_longer_than_500_lines_without_saying_why() -> None:
    assert long_files_without_a_reason(PACKAGE) == []


def test_the_length_check_sees_long_files(tmp_path: Path) -> None:
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "short.py").write_text('"""Short."""\n' + "x = 1\n" * (MAX_LINES - 1))
    (package / "long.py").write_text('"""Long."""\n' + "x = 1\n" * MAX_LINES)
    (package / "comment.py").write_text(f"# {LONG_FILE_REASON} it must be\n" + "x = 1\n" * MAX_LINES)
    (package / "told.py").write_text(f'"""Long.\n\nIt is {LONG_FILE_REASON} it must be.\n"""\n' + "x = 1\n" * MAX_LINES)
    assert long_files_without_a_reason(package) == [f"pkg/comment.py: {MAX_LINES + 1} lines",
                                                    f"pkg/long.py: {MAX_LINES + 1} lines"]
