"""The README's "Use with your library" examples, each run as a user would: a fresh interpreter, its own folder."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MARKER = re.compile(r"<!-- example: (\w+) -->\n```python\n(.*?)```", re.S)
SLOW = {"sb3", "minari", "lerobot", "torchrl"}  # a torch stack to import, a dataset to download
NEEDS = {"minari": ["lerobot"]}  # run first, in the same folder (the dataset it downloads)
FROM_CHECKOUT = {"rliable"}  # reads the shipped submissions/


def examples() -> dict[str, str]:
    """The README's examples by name."""
    found = dict(MARKER.findall((REPO / "README.md").read_text()))
    assert found, "no examples found in README.md"
    return found


def run_example(code: str, cwd: Path, home: Path) -> str:
    """Run one example in a fresh interpreter (this checkout first on the path, the Hub forbidden)."""
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", "HF_HOME": str(home),
           "HF_HUB_OFFLINE": "1", "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"}
    env.pop("MINARI_DATASETS_PATH", None)
    done = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_every_library_has_an_example() -> None:
    assert set(examples()) == {"gymnasium", "sb3", "torchrl", "cleanrl", "lerobot", "minari", "rliable"}


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n
                                  for n in ("gymnasium", "sb3", "torchrl", "cleanrl", "lerobot", "minari", "rliable")])
def test_the_readme_example_runs(name: str, tmp_path: Path) -> None:
    code = examples()
    for first in NEEDS.get(name, []):
        run_example(code[first], tmp_path, tmp_path / "hf")
    out = run_example(code[name], REPO if name in FROM_CHECKOUT else tmp_path, tmp_path / "hf")
    assert out.strip(), f"the {name} example printed nothing"
