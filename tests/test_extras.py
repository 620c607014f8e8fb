"""The lean install: heavy dependencies are extras, and a missing one is a clear error naming the extra."""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path
from typing import Any, Callable

import pytest
from typer.testing import CliRunner

from mewa_bench.agents import rl2
from mewa_bench.datasets.downloader import download
from mewa_bench.datasets.lerobot_recorder import LeRobotSink
from mewa_bench.envs.sb3 import make_sb3_vec_env
from mewa_bench.extras import MissingExtra, require
from mewa_bench.logs import McapSink, RerunSink
from mewa_bench.protocol.trajectory import RunInfo

REPO = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
EXTRAS: dict[str, list[str]] = PROJECT["optional-dependencies"]
HEAVY = {"torch", "lerobot", "sapien", "rerun-sdk", "mcap", "ray", "huggingface-hub", "stable-baselines3", "torchrl",
         "minari"}
RUNTIME_EXTRAS = {"logs", "datasets", "sapien", "train", "ray", "service", "interop"}
RUN = RunInfo("a", "0" * 64, "narrow-v1", "1" * 64, (0,), 10, "mewa/MEWA-v0", "v0", "0.1.0")


def package_name(requirement: str) -> str:
    """'lerobot[dataset]==0.6.1' -> 'lerobot'; names normalised as pip does ('huggingface_hub' -> 'huggingface-hub')."""
    return re.split(r"[\[=<>!~;@ ]", requirement, maxsplit=1)[0].lower().replace("_", "-")


def expand(extra: str) -> set[str]:
    """The requirements an extra installs, following self-references such as `mewa-bench[logs,ray]`."""
    found: set[str] = set()
    for requirement in EXTRAS[extra]:
        if package_name(requirement) == "mewa-bench":
            for name in re.search(r"\[(.*)\]", requirement).group(1).split(","):
                found |= expand(name.strip())
        else:
            found.add(requirement)
    return found


def hide(monkeypatch: pytest.MonkeyPatch, package: str) -> None:
    """Make `package` unimportable, as if not installed (`sys.modules[name] = None`), for one test."""
    for name in [m for m in sys.modules if m.startswith(package + ".")]:
        monkeypatch.delitem(sys.modules, name)  # cached submodules would be found without their parent
    monkeypatch.setitem(sys.modules, package, None)


# -- (a) pyproject: a light core, heavy extras, `all` covering them -----------------------------------------------

def test_core_dependencies_are_light() -> None:
    core = {package_name(r) for r in PROJECT["dependencies"]}
    assert core == {"numpy", "scipy", "gymnasium", "typer", "rich", "matplotlib"}
    assert not core & HEAVY


def test_every_runtime_extra_exists_and_all_covers_them() -> None:
    assert set(EXTRAS) == RUNTIME_EXTRAS | {"all", "test"}
    assert expand("all") == set().union(*(expand(e) for e in RUNTIME_EXTRAS))
    assert HEAVY <= {package_name(r) for r in expand("all")}


def test_every_requirement_is_pinned() -> None:
    for requirement in PROJECT["dependencies"] + [r for rs in EXTRAS.values() for r in rs]:
        assert package_name(requirement) == "mewa-bench" or "==" in requirement, requirement


def test_ci_installs_every_extra() -> None:
    assert "-e '.[all,test]'" in (REPO / ".ci" / "setup").read_text()


# -- (b) the helper ---------------------------------------------------------------------------------------------

def test_require_returns_the_module() -> None:
    assert require("json.decoder", "logs", "x").JSONDecoder is not None


def test_a_missing_package_names_the_extra_and_the_pip_command(monkeypatch: pytest.MonkeyPatch) -> None:
    hide(monkeypatch, "lerobot")
    with pytest.raises(MissingExtra) as err:
        require("lerobot.datasets.lerobot_dataset", "datasets", "`mewa-bench record`")
    assert str(err.value) == ("`mewa-bench record` needs the datasets extra (lerobot is not installed): "
                              "pip install 'mewa-bench[datasets]'")
    assert isinstance(err.value, ImportError) and (err.value.module, err.value.extra) == (
        "lerobot.datasets.lerobot_dataset", "datasets")


def test_a_package_that_fails_to_import_says_why(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "mewa_broken_pkg.py").write_text("raise ImportError('libfoo.so: cannot open shared object file')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(MissingExtra, match=r"needs the train extra \(importing mewa_broken_pkg failed: libfoo.so"):
        require("mewa_broken_pkg", "train", "x")


# Every place the package uses an extra: (hidden package, extra named, the call, given a temporary folder).
CALL_SITES: dict[str, tuple[str, str, Callable[[Path], Any]]] = {
    "--log mcap": ("mcap", "logs", lambda tmp: McapSink(tmp / "run.mcap").start(RUN)),
    "--log rerun": ("rerun", "logs", lambda tmp: RerunSink(tmp / "run.rrd").start(RUN)),
    "record": ("lerobot", "datasets", lambda tmp: LeRobotSink(tmp / "dataset", "mewa/dataset").start(RUN)),
    "datasets download": ("huggingface_hub", "datasets", lambda tmp: download("someone/mewa-data", None, tmp / "d")),
    "train rl2": ("torch", "train", lambda tmp: rl2.train(rl2.Settings(total_steps=1), tmp / "run")),
    "rl2 checkpoint": ("torch", "train", lambda tmp: rl2.RL2Agent(tmp / "checkpoint.pt")),
    "sb3 vec env": ("stable_baselines3", "interop", lambda tmp: make_sb3_vec_env(num_envs=2)),
}


@pytest.mark.parametrize("site", CALL_SITES)
def test_every_call_site_names_its_extra(site: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    package, extra, call = CALL_SITES[site]
    hide(monkeypatch, package)
    with pytest.raises(MissingExtra, match=re.escape(f"needs the {extra} extra ({package} is not installed): "
                                                     f"pip install 'mewa-bench[{extra}]'")):
        call(tmp_path)
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]  # it failed before writing anything


def test_sapien_mode_without_sapien_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    from mewa_bench.render import device

    monkeypatch.setattr(device, "_active", None)
    hide(monkeypatch, "sapien")
    with pytest.raises(device.RenderUnavailable, match=re.escape("needs the sapien extra (sapien is not installed)")):
        device.require_render_device()


# -- (c) the command line -------------------------------------------------------------------------------------

def test_the_cli_reports_a_missing_extra_cleanly(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from mewa_bench.cli import app

    hide(monkeypatch, "lerobot")
    out = tmp_path / "dataset"
    result = CliRunner().invoke(app, ["record", "--policy", "random", "--seeds", "1", "--pairs", "0", "--out", str(out)],
                                env={"COLUMNS": "200"})
    text = " ".join(result.output.split())
    assert result.exit_code == 1, result.output
    assert ("error: recording a LeRobot dataset (`mewa-bench record`) needs the datasets extra (lerobot is not "
            "installed): pip install 'mewa-bench[datasets]'") in text
    assert "Traceback" not in result.output and not isinstance(result.exception, MissingExtra)
    assert not out.exists()


def test_the_cli_reports_a_missing_extra_through_or_exit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from mewa_bench.cli import app

    hide(monkeypatch, "torch")
    result = CliRunner().invoke(app, ["train", "rl2", "--steps", "1", "--out", str(tmp_path / "run")],
                                env={"COLUMNS": "200"})
    assert result.exit_code == 1, result.output
    assert "needs the train extra (torch is not installed): pip install 'mewa-bench[train]'" in " ".join(
        result.output.split())
    assert "Traceback" not in result.output


# -- (d) Gymnasium's checker on a core install ----------------------------------------------------------------------

@pytest.mark.parametrize("env_id", ["mewa/MEWA-v0", "mewa/MEWA-Meta-v0"])
def test_check_env_passes_without_the_extras(env_id: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Render modes included: without sapien the envs offer "ansi" only, and Gymnasium's checker is silent."""
    import warnings

    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env

    import mewa_bench  # noqa: F401 - registers the env ids
    from mewa_bench.envs import MewaEnv

    for package in ("sapien", "torch", "lerobot", "rerun", "mcap"):
        hide(monkeypatch, package)
    env = gym.make(env_id, disable_env_checker=True)
    assert env.metadata["render_modes"] == ["ansi"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    # The one warning left says the env is wrapped (gym.make's order enforcing, MEWA-Meta's MetaEpisode).
    assert [str(w.message) for w in caught if "different from the unwrapped" not in str(w.message)] == []
    with pytest.raises(Exception, match="needs the sapien extra"):
        MewaEnv(render_mode="rgb_array")
