"""The learned baselines' tuning budget: a few settings per algorithm, one seed, 2 M steps, scored on validation pairs.

Each configuration is trained on narrow-v2 and wide-v2 (`mewa-bench train ... --set ...`) and evaluated on the
suite's validation suite (`<suite>-validation`: held-out meta-train workers, never the test pairs). A variant
replaces an algorithm's defaults only if its validation mean score beats theirs by more than MARGIN.

    python scripts/tune_baselines.py run [--suite narrow-v2] [--algo rl2]   # train and evaluate what is missing
    python scripts/tune_baselines.py report                                 # the table and the selection

Runs go to runs/tuning/<algo>-<config>-<suite>-seed1 (resumable: finished runs are skipped);
the summary to docs/tuning.csv.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUNS = ROOT / "runs" / "tuning"
SUMMARY = ROOT / "docs" / "tuning.csv"
CLI = [str(Path(sys.executable).with_name("mewa-bench"))]
SUITES = ("narrow-v2", "wide-v2")
STEPS = 2_000_000
SEED = 1
VALIDATION_SEEDS = {"narrow-v2": 64, "wide-v2": 16}  # 1,024 and 1,280 units
MARGIN = 0.01  # a variant must beat the defaults' validation mean by more than this to replace them
GRID = {  # algorithm -> configuration name -> settings changed (the same three questions for every algorithm)
    "varibad": {"default": {}, "lr-0.3x": {"learning_rate": 2.1e-4}, "ent-0.1x": {"ent_coef": 0.001},
                "step-rewards": {"step_rewards": True}},
    "maml": {"default": {}, "lr-0.3x": {"learning_rate": 3e-4}, "ent-0.1x": {"ent_coef": 0.001},
             "inner-lr-2x": {"inner_lr": 0.1}},
    "pearl": {"default": {}, "lr-0.3x": {"learning_rate": 3e-4}, "ent-0.3x": {"target_entropy_ratio": 0.05},
              "kl-10x": {"kl_weight": 1.0}},
    "rl2": {"default": {}, "lr-0.3x": {"learning_rate": 3e-4}, "ent-0.1x": {"ent_coef": 0.001},
            "step-rewards": {"step_rewards": True}},
}


def folder(algo: str, config: str, suite: str) -> Path:
    """The run folder of one configuration on one suite."""
    return RUNS / f"{algo}-{config}-{suite}-seed{SEED}"


def results_path(algo: str, config: str, suite: str) -> Path:
    """Its validation results file."""
    return folder(algo, config, suite) / f"results-{suite}-validation.json"


def finished(algo: str, config: str, suite: str) -> bool:
    """Whether the configuration's validation run is complete (an interrupted one is redone)."""
    path = results_path(algo, config, suite)
    return path.exists() and json.loads(path.read_text()).get("complete") is True


def run_one(algo: str, config: str, suite: str) -> None:
    """Train one configuration (unless its checkpoint is there) and evaluate it on the validation suite."""
    out = folder(algo, config, suite)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    if not (out / "run.json").exists():
        sets = [f"--set={k}={json.dumps(v) if isinstance(v, bool) else v}" for k, v in GRID[algo][config].items()]
        subprocess.run([*CLI, "train", algo, "--suite", suite, "--seed", str(SEED), "--steps", str(STEPS), "--resume",
                        *sets, "--algorithm", f"{algo}-{config}", "--out", str(out)], check=True, env=env,
                       stdout=subprocess.DEVNULL)
    subprocess.run([*CLI, "evaluate", str(out / "agent.py"), "--suite", f"{suite}-validation", "--seeds",
                    str(VALIDATION_SEEDS[suite]), "--name", f"{algo}-{config}", "--out",
                    str(results_path(algo, config, suite)), "--overwrite"], check=True, env=env,
                   stdout=subprocess.DEVNULL)


def summary_rows() -> list[dict]:
    """One row per finished configuration: validation mean, adaptability and the paired gap to the best fixed policy."""
    rows = []
    for suite in SUITES:
        for algo, configs in GRID.items():
            for config, changed in configs.items():
                if not finished(algo, config, suite):
                    continue
                scores = json.loads(results_path(algo, config, suite).read_text())["scores"]
                mean, adapt = scores["mean"], scores["adaptability"]
                rows.append({"suite": suite, "algorithm": algo, "config": config,
                             "settings": " ".join(f"{k}={v}" for k, v in changed.items()) or "defaults",
                             "validation_mean": f"{mean['mean']:.4f}", "mean_low": f"{mean['low']:.4f}",
                             "mean_high": f"{mean['high']:.4f}", "adaptability": f"{adapt['mean']:+.4f}",
                             "steps": STEPS, "seed": SEED})
    return rows


def selection(rows: list[dict]) -> dict[tuple[str, str], str]:
    """(suite, algorithm) -> the configuration chosen: the best validation mean if it beats the defaults by MARGIN."""
    chosen = {}
    for suite in SUITES:
        for algo in GRID:
            mine = {r["config"]: float(r["validation_mean"]) for r in rows if (r["suite"], r["algorithm"]) == (suite, algo)}
            if "default" not in mine:
                continue
            best = max(mine, key=lambda c: (mine[c], c == "default"))
            chosen[(suite, algo)] = best if mine[best] > mine["default"] + MARGIN else "default"
    return chosen


def report() -> None:
    """Write docs/tuning.csv and print the table as markdown."""
    rows = summary_rows()
    chosen = selection(rows)
    for row in rows:
        row["selected"] = "yes" if chosen.get((row["suite"], row["algorithm"])) == row["config"] else ""
    SUMMARY.parent.mkdir(parents=True, exist_ok=True)
    with SUMMARY.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]) if rows else ["suite"])
        writer.writeheader()
        writer.writerows(rows)
    print("| suite | algorithm | configuration | settings | validation mean [95% CI] | adaptability | selected |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['suite']} | {r['algorithm']} | {r['config']} | {r['settings']} | {r['validation_mean']} "
              f"[{r['mean_low']}, {r['mean_high']}] | {r['adaptability']} | {r['selected']} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=["run", "report"])
    parser.add_argument("--suite", action="append", choices=SUITES)
    parser.add_argument("--algo", action="append", choices=list(GRID))
    args = parser.parse_args()
    if args.what == "report":
        report()
        return
    for suite in args.suite or SUITES:
        for algo in args.algo or GRID:
            for config in GRID[algo]:
                if finished(algo, config, suite):
                    continue
                print(f"{algo} {config} on {suite}", flush=True)
                run_one(algo, config, suite)


if __name__ == "__main__":
    main()
