"""Suites v2: two worker families, gap-maximising curation, a meta-train mixture that covers the test region.

Expectations are derived by hand here (boxes, monotone orders, grid, greedy optimality of every
phase-2 pick), not through the generator's own helpers, wherever that is possible.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from scipy.stats import mannwhitneyu

import mewa_bench  # noqa: F401
from mewa_bench.design import exact
from mewa_bench.design.generate import GAP_TARGETS, generate_suite
from mewa_bench.design.policies import PolicyAgent, policy_names
from mewa_bench.design.suites import SHIPPED_SUITES, V2_SUITES, Suite, content_hash, load_suite, shipped_path, suite_text
from mewa_bench.game.distributions import meta_test_candidates, sample_meta_train_workers, sample_train_workers
from mewa_bench.game.task import Task

ROOT = Path(__file__).resolve().parents[1]


def boxes(task: Task) -> list[tuple[np.ndarray, np.ndarray]]:
    """(centre, sigma) of both families, by hand: the paper's, and its mirror image."""
    avg, sigma = np.array(task.average_worker), np.array(task.sigma)
    return [(avg, sigma), (avg[::-1], sigma[::-1])]


def outside_every_box(task: Task, w: np.ndarray) -> bool:
    """Some component at >= 2 sigma from the centre, for each family."""
    return all(any(abs(w[x] - c[x]) >= 2 * s[x] - 1e-12 for x in range(task.N)) for c, s in boxes(task))


def monotone_kind(w: np.ndarray) -> set[str]:
    """Which of the two orders a worker keeps."""
    kinds = set()
    if all(w[x] >= w[x + 1] for x in range(len(w) - 1)):
        kinds.add("paper")
    if all(w[x] <= w[x + 1] for x in range(len(w) - 1)):
        kinds.add("overloaded")
    return kinds


def grid_distance(w: np.ndarray) -> np.ndarray:
    """L-inf distance of each row to the nearest point of the 0.05 grid."""
    return np.abs(w - np.round(w / 0.05) * 0.05).max(axis=-1)


def task_pairs(suite: Suite, t: int) -> list:
    return [p for p in suite.pairs if p.task_index == t]


@pytest.mark.parametrize("name", V2_SUITES)
def test_v2_suite_loads_matches_its_hash_and_keeps_the_v1_pair_format(name: str) -> None:
    suite = load_suite(name)
    assert suite.name == name and suite.sha256 == content_hash(suite.content)
    assert shipped_path(name).read_text() == suite_text(suite.content)
    v1 = load_suite(name.replace("v2", "v1"))
    assert set(suite.summary) == set(v1.summary)
    for p in suite.pairs:
        assert set(v1.pairs[0].data) <= set(p.data)
        assert set(p.data["baselines"]) == {"random", "random_task_specific", "max_expected"}
    assert suite.content["env_id"] == "mewa/MEWA-v0" and suite.content["version"] == 2


@pytest.mark.parametrize("kind", ["narrow-v2", pytest.param("wide-v2", marks=pytest.mark.slow)])  # narrow by default, wide (30-100 s) slow
def test_generate_reproduces_the_v2_file_byte_for_byte(kind: str) -> None:
    assert suite_text(generate_suite(kind)) == shipped_path(kind).read_text()


def test_v1_suites_are_untouched() -> None:
    assert SHIPPED_SUITES == ("narrow-v1", "wide-v1")
    hashes = {"narrow-v1": "fb6d78a362c397d7b5984ef9a2cb0a1feccc7e0d5e5a2446a5591a0b91420eb8",
              "wide-v1": "215f43628bbcf7985df4003f41c0791d0889f96d7b444dfd376f9851d4448b68"}
    for name, digest in hashes.items():
        suite = load_suite(name)
        assert suite.sha256 == digest
        for t, task in enumerate(suite.tasks):  # v1 tasks: the paper's family and candidates only
            assert "worker_distribution" not in task.extra
            cands = meta_test_candidates(task)
            assert all(monotone_kind(w) >= {"paper"} for w in cands)
            assert len(cands) == suite.content["tasks"][t]["curation"]["candidates"]
    task = load_suite("narrow-v1").tasks[0]
    a = sample_train_workers(task, np.random.default_rng(5), 300)
    b = sample_meta_train_workers(task, np.random.default_rng(5), 300)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", V2_SUITES)
def test_curated_workers_follow_the_test_region_and_curation_rules(name: str) -> None:
    suite = load_suite(name)
    names_seen: set[str] = set()
    for t, task in enumerate(suite.tasks):
        pairs = task_pairs(suite, t)
        fams = task.extra["worker_distribution"]["families"]
        for f, (c, s) in zip(fams, boxes(task)):
            np.testing.assert_allclose(f["average_worker"], c)
            np.testing.assert_allclose(f["sigma"], s)
        workers = [np.array(p.worker.w) for p in pairs]
        for p, w in zip(pairs, workers):
            kinds = monotone_kind(w)
            assert kinds, f"{w} keeps neither order"
            assert set(p.data["family"].split("+")) == kinds
            names_seen |= kinds
            assert np.allclose(w / 0.05, np.round(w / 0.05), atol=1e-9), "not on the 0.05 grid"
            assert outside_every_box(task, w)
            assert p.data["baselines"]["max_expected"] >= 0.5
        phase1 = [i for i, p in enumerate(pairs) if p.data["phase"] == 1]
        assert phase1 == list(range(len(phase1))) and len(phase1) >= 1
        for i, j in itertools.combinations(phase1, 2):
            assert mannwhitneyu(pairs[i].data["toptimal"], pairs[j].data["toptimal"]).pvalue <= 0.05
        for j in range(len(phase1), len(pairs)):
            assert all(np.abs(workers[j] - workers[i]).max() >= 0.2 - 1e-9 for i in range(j))
        assert len(pairs) == (16 if suite.content["suite"] == "narrow" else 8)
    assert names_seen == {"paper", "overloaded"}


def test_every_narrow_v2_phase2_pick_maximises_the_gap() -> None:
    suite = load_suite("narrow-v2")
    task = suite.tasks[0]
    grid = np.array([w for w in itertools.product(np.round(np.arange(21) * 0.05, 12), repeat=4)
                     if monotone_kind(np.array(w)) and outside_every_box(task, np.array(w))])
    values = exact.expected_returns(task, policy_names(4, baselines=False), grid).T
    keep = values.max(axis=1) >= 0.5
    grid, values = grid[keep], values[keep]
    loss = 1.0 - values / values.max(axis=1, keepdims=True)
    index = {tuple(np.round(w, 9)): i for i, w in enumerate(grid)}
    chosen = [index[tuple(np.round(p.worker.w, 9))] for p in suite.pairs]
    phase1 = sum(p.data["phase"] == 1 for p in suite.pairs)
    for k in range(phase1, len(chosen)):
        before = chosen[:k]
        allowed = np.array([all(np.abs(grid[c] - grid[b]).max() >= 0.2 - 1e-9 for b in before) for c in range(len(grid))])
        gaps = (loss[before].sum(axis=0) + loss).min(axis=1) / (k + 1)
        assert allowed[chosen[k]]
        assert gaps[chosen[k]] >= gaps[allowed].max() - 1e-9


@pytest.mark.parametrize("name", V2_SUITES)
def test_gap_targets_and_best_fixed_policy(name: str) -> None:
    suite = load_suite(name)
    gap = suite.summary["non_adaptive_gap"]
    assert gap >= GAP_TARGETS[name]
    assert gap == pytest.approx(1.0 - np.mean([p.data["best_fixed"] / p.max_expected for p in suite.pairs]), abs=1e-11)
    for t in range(len(suite.tasks)):
        values = np.array([p.data["toptimal"] for p in task_pairs(suite, t)])
        ratio = values / values.max(axis=1, keepdims=True)
        best = int(np.argmax(ratio.mean(axis=0)))
        np.testing.assert_allclose([p.data["best_fixed"] for p in task_pairs(suite, t)], values[:, best], atol=1e-12)


def _monte_carlo(task: Task, worker: tuple[float, ...], policy: str, episodes: int, seed: int) -> np.ndarray:
    """Normalised returns of a PolicyAgent playing MewaEnv with a fixed worker."""
    env = gym.make("mewa/MEWA-v0", task=task, worker=worker)
    agent = PolicyAgent(policy, task, np.random.default_rng(seed))
    out = np.empty(episodes)
    for e in range(episodes):
        obs, _ = env.reset(seed=seed * 100_000 + e)
        agent.reset()
        done, info = False, {}
        while not done:
            obs, _, terminated, truncated, info = env.step(agent.act_observation(obs))
            done = terminated or truncated
        out[e] = info["normalised_return"]
    return out


@pytest.mark.parametrize("name,family", [("narrow-v2", "paper"), ("narrow-v2", "overloaded"),
                                         ("wide-v2", "paper"), ("wide-v2", "overloaded")])
def test_exact_values_agree_with_monte_carlo(name: str, family: str) -> None:
    suite = load_suite(name)
    pair = next(p for p in suite.pairs if p.data["family"] == family and suite.tasks[p.task_index].N == (4 if name == "narrow-v2" else 3))
    task = suite.tasks[pair.task_index]
    names = policy_names(task.N, baselines=False)
    fixed = names[pair.data["toptimal"].index(pair.data["best_fixed"])]
    checks = [(pair.data["best_policy"], pair.data["baselines"]["max_expected"]), (fixed, pair.data["best_fixed"]),
              ("random-task-specific", pair.data["baselines"]["random_task_specific"])]
    for k, (policy, expected) in enumerate(checks):
        sample = _monte_carlo(task, pair.worker.w, policy, 600, seed=7 + k)
        se = sample.std(ddof=1) / np.sqrt(len(sample))
        assert abs(sample.mean() - expected) <= 4.5 * se + 1e-9, (policy, pair.worker.w, sample.mean(), expected, se)


@pytest.mark.parametrize("name", V2_SUITES)
def test_meta_train_mixture_never_meets_the_test_set_and_covers_it(name: str) -> None:
    suite = load_suite(name)
    rng = np.random.default_rng(11)
    for t, task in enumerate(suite.tasks[:3]):
        train = sample_meta_train_workers(task, rng, 6000)
        kinds = [monotone_kind(w) for w in train]
        assert all(kinds)
        share = np.mean(["overloaded" in k for k in kinds])
        assert 0.45 < share < 0.55
        assert (grid_distance(train) >= 0.01 - 1e-12).all()
        curated = np.array([p.worker.w for p in task_pairs(suite, t)])
        assert (np.abs(train[:, None, :] - curated[None, :, :]).max(axis=2) >= 0.01 - 1e-12).all()
        outside = np.mean([outside_every_box(task, w) for w in train[:2000]])
        assert outside > 0.3, "the mixture must reach the test region's structure, not only the boxes"
        # Every policy that is best on a curated worker is also best on some meta-train workers.
        names = policy_names(task.N, baselines=False)
        best_train = set(np.argmax(exact.expected_returns(task, names, train[:1500]), axis=0).tolist())
        best_curated = {names.index(p.data["best_policy"]) for p in task_pairs(suite, t)}
        assert best_curated <= best_train


def test_envs_sample_the_v2_mixture_and_the_default_env_stays_v1() -> None:
    tasks = load_suite("narrow-v2").tasks
    env = gym.make("mewa/MEWA-v0", tasks=tasks)
    env.reset(seed=3)
    seen = []
    for _ in range(200):
        env.reset()
        seen.append(np.array(env.unwrapped.worker.w))
    seen = np.array(seen)
    assert (grid_distance(seen) >= 0.01 - 1e-12).all()
    assert any("overloaded" in monotone_kind(w) and "paper" not in monotone_kind(w) for w in seen)
    assert any("paper" in monotone_kind(w) and "overloaded" not in monotone_kind(w) for w in seen)
    default = gym.make("mewa/MEWA-v0")
    default.reset(seed=0)
    assert default.unwrapped.task == load_suite("narrow-v1").tasks[0]
    for _ in range(50):
        default.reset()
        w = np.array(default.unwrapped.worker.w)
        assert monotone_kind(w) >= {"paper"}


def test_report_and_gap_script_show_the_v2_targets() -> None:
    text = (ROOT / "docs" / "suites.md").read_text()
    for name in V2_SUITES:
        suite = load_suite(name)
        assert suite.sha256 in text
        assert f"**{suite.summary['non_adaptive_gap']:.4f}** (target >= {GAP_TARGETS[name]:.2f}: met)" in text
    assert "overloaded" in text and "Meta-train distribution" in text
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "suite_gaps.py")], capture_output=True, text=True, check=False)
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.count(" met ") == 2
