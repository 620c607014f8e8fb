"""SAPIEN mode end to end: image observations, and images in MCAP, Rerun and LeRobot outputs."""

from __future__ import annotations

import base64
import io
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from mewa_bench.design.suites import load_suite
from mewa_bench.envs import MewaEnv
from mewa_bench.protocol import policy_agent
from mewa_bench.protocol.config import EvalConfig
from mewa_bench.protocol.runner import evaluate
from mewa_bench.render.device import RenderUnavailable, require_render_device

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module", autouse=True)
def render_device() -> None:
    try:
        require_render_device()
    except RenderUnavailable as e:
        if os.environ.get("MEWA_REQUIRE_RENDER", "").strip() not in ("", "0"):
            pytest.fail(f"MEWA_REQUIRE_RENDER is set but rendering is unavailable: {e}")
        pytest.skip(f"no render device: {e}")


def test_env_in_sapien_mode_passes_check_env_and_renders_its_state() -> None:
    suite = load_suite("narrow-v1")
    task, worker = suite.tasks[0], suite.pairs[3].worker.w
    env = MewaEnv(task=task, worker=worker, mode="sapien", image_size=(96, 64), render_mode="rgb_array")
    check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=0)
    assert obs["state"].shape == (18,) and obs["image"].shape == (96, 64, 3) and obs["image"].dtype == np.uint8
    assert env.observation_space.contains(obs)
    seen = {obs["image"].tobytes()}
    for action in (3, 3, 1, 3):
        obs, *_ = env.step(action)
        np.testing.assert_array_equal(env.render(), obs["image"])
        seen.add(obs["image"].tobytes())
    assert len(seen) == 5  # every step changed the state, and so the picture
    # Same rules: the state part equals the vector env's observation.
    vector = MewaEnv(task=task, worker=worker)
    vector.reset(seed=0)
    env.reset(seed=0)
    np.testing.assert_array_equal(vector.step(3)[0], env.step(3)[0]["state"])


def test_sapien_mode_without_a_device_fails_at_once_with_install_hint(tmp_path: Path) -> None:
    env = {**os.environ, "VK_ICD_FILENAMES": str(tmp_path / "missing_icd.json")}
    result = subprocess.run([str(REPO / ".venv" / "bin" / "mewa-bench"), "evaluate",
                             str(REPO / "submissions" / "random" / "agent.py"), "--mode", "sapien",
                             "--out", str(tmp_path / "r.json")], capture_output=True, text=True, env=env)
    text = " ".join(result.stdout.split())
    assert result.returncode == 1 and "install-vulkan" in text, result.stdout + result.stderr
    assert not (tmp_path / "r.json").exists()


def test_evaluate_and_record_in_sapien_mode_write_images_everywhere(tmp_path: Path, monkeypatch) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from PIL import Image

    from mewa_bench.datasets import LeRobotSink
    from mewa_bench.logs import McapSink, RerunSink
    from mewa_bench.render import SceneRenderer
    from mewa_bench.game.rules import initial_state

    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    config = EvalConfig(agent_path=policy_agent.AGENT_FILE, out=tmp_path / "r.json", seeds=(0,), pairs=(2,),
                        agent_args={"policy": "max-expected"}, privileged=True, mode="sapien", image_size=(64, 64))
    sinks = [McapSink(tmp_path / "run.mcap"), RerunSink(tmp_path / "run.rrd"), LeRobotSink(tmp_path / "ds", "mewa/img")]
    results, _ = evaluate(config, sinks=sinks)
    assert results["env"]["mode"] == "sapien" and results["env"]["image_size"] == [64, 64]
    steps = sum(results["units"][0]["lengths"])
    task = load_suite("narrow-v1").tasks[0]
    start = SceneRenderer(64, 64).render(task, initial_state(task))

    # MCAP: one foxglove.CompressedImage per step plus each episode's first frame, PNG-decodable.
    from mcap.reader import make_reader

    with open(tmp_path / "run.mcap", "rb") as f:
        frames = [json.loads(m.data) for _, c, m in make_reader(f).iter_messages() if c.topic == "/mewa/camera"]
    assert len(frames) == steps + 10
    first = np.asarray(Image.open(io.BytesIO(base64.b64decode(frames[0]["data"]))).convert("RGB"))
    np.testing.assert_array_equal(first, start)

    # Rerun: one camera image per step.
    from rerun.chunk import RrdReader

    rows = sum(len(c.to_record_batch()) for c in RrdReader(tmp_path / "run.rrd").stream()
               if c.entity_path == "/mewa/camera" and not c.is_static)
    assert rows == steps

    # LeRobot: observation.images.top on every frame; frame 0 is the initial scene (PNG: lossless).
    ds = LeRobotDataset("mewa/img", root=tmp_path / "ds", video_backend="pyav")
    assert ds.num_frames == steps and "observation.images.top" in ds.features
    image = ds[0]["observation.images.top"]
    pixels = np.round(image.numpy().transpose(1, 2, 0) * 255).astype(np.uint8)
    np.testing.assert_array_equal(pixels, start)


def test_a_vector_agent_gets_batches_of_images_and_plays_as_in_vector_mode(tmp_path: Path) -> None:
    vector = Path(__file__).parent / "agents" / "vector_agent.py"  # asserts images [n, H, W, 3] uint8 per batch
    args = {"agent_path": vector, "seeds": (0, 1), "pairs": (2, 5), "lanes": 4, "agent_args": {"sampled": "true"}}
    images, _ = evaluate(EvalConfig(out=tmp_path / "sapien.json", mode="sapien", image_size=(32, 32), **args))
    plain, _ = evaluate(EvalConfig(out=tmp_path / "vector.json", **args))
    assert images["env"]["mode"] == "sapien" and len(images["units"]) == 4
    assert images["units"] == plain["units"]
