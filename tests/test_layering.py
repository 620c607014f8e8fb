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
    return ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts).removesuffix(".__init__")


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
