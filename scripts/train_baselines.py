"""The shipped learned baselines at the paper's protocol: 5 training seeds on the narrow suites, 3 on the wide ones.

One run is `mewa-bench train ALGO --suite S --seed N --steps 4000000 [--set ...] --out submissions/ALGO-S-seedN`,
then `mewa-bench evaluate` of its agent.py with the suite's default seeds into the folder's results file. The
settings are each algorithm's defaults on the v1 suites and, on narrow-v2 and wide-v2, the configuration the
tuning budget selected there (docs/tuning.csv, written by `scripts/tune_baselines.py report`). An algorithm whose
tuning on a v2 suite has not finished gets no runs there, and a shipped run trained with other settings than the
selection is reported, never mixed in: retrain it, or rename it as its own algorithm.

    python scripts/train_baselines.py status                       # shipped, missing and mismatched runs
    python scripts/train_baselines.py run [--suite S] [--algo A]   # train and evaluate what is missing, one at a time
    python scripts/train_baselines.py readmes                      # every learned run's README: its results section

Runs are independent: start two `run`s with different --suite or --algo to use two cores. A run interrupted while
training resumes from its checkpoint (`train --resume`); one interrupted while evaluating is evaluated again.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tune_baselines import GRID, SUMMARY  # noqa: E402 (the tuning grid and its summary are the selection's source)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from mewa_bench.protocol.results import read_results  # noqa: E402

CLI = [str(Path(sys.executable).with_name("mewa-bench"))]
SEEDS = {"narrow-v1": 5, "wide-v1": 3, "narrow-v2": 5, "wide-v2": 3}  # the paper's counts: 5 narrow, 3 wide
ALGOS = ("rl2", "varibad", "pearl", "maml")
STEPS = 4_000_000
TUNED = ("narrow-v2", "wide-v2")


def selected_settings(suite: str, algo: str) -> dict[str, object] | None:
    """The settings a run of `algo` on `suite` uses ({}: the defaults); None while its tuning is unfinished."""
    if suite not in TUNED:
        return {}
    with SUMMARY.open(newline="") as f:
        chosen = [r["config"] for r in csv.DictReader(f)
                  if (r["suite"], r["algorithm"], r["selected"]) == (suite, algo, "yes")]
    return dict(GRID[algo][chosen[0]]) if chosen else None


def folder(algo: str, suite: str, seed: int) -> Path:
    """A run's submission folder."""
    return ROOT / "submissions" / f"{algo}-{suite}-seed{seed}"


def results(algo: str, suite: str, seed: int) -> Path:
    """Its ranked results file."""
    return folder(algo, suite, seed) / f"results-{suite}.json"


def run_settings(algo: str, suite: str, seed: int) -> dict[str, object]:
    """The settings a shipped run was trained with (run.json's `settings`, as `--set` gave them)."""
    info = json.loads((folder(algo, suite, seed) / "run.json").read_text())
    return {k: v for k, v in info.get("settings", {}).items() if k != "dataset"}


def same_settings(given: dict[str, object], wanted: dict[str, object]) -> bool:
    """Whether `--set` values recorded as text equal the selection's (numbers compared as numbers)."""
    def value(v: object) -> object:
        try:
            return float(v)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            return str(v).lower()
    return {k: value(v) for k, v in given.items()} == {k: value(v) for k, v in wanted.items()}


def plan(suites: list[str], algos: list[str]) -> list[tuple[str, str, int, str]]:
    """(suite, algorithm, seed, state) for every run the protocol asks for: shipped, missing, untuned or mismatched."""
    out = []
    for suite in suites:
        for algo in algos:
            wanted = selected_settings(suite, algo)
            for seed in range(1, SEEDS[suite] + 1):
                if results(algo, suite, seed).exists():
                    state = "shipped" if wanted is None or same_settings(run_settings(algo, suite, seed), wanted) \
                        else "other settings"
                else:
                    state = "untuned" if wanted is None else "missing"
                out.append((suite, algo, seed, state))
    return out


def run_one(algo: str, suite: str, seed: int) -> None:
    """Train (or resume) one run, then evaluate it with the suite's default seeds."""
    out = folder(algo, suite, seed)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    sets = [f"--set={k}={json.dumps(v) if isinstance(v, bool) else v}"
            for k, v in (selected_settings(suite, algo) or {}).items()]
    subprocess.run([*CLI, "train", algo, "--suite", suite, "--seed", str(seed), "--steps", str(STEPS), *sets,
                    "--resume", "--out", str(out.relative_to(ROOT))], check=True, env=env, cwd=ROOT,
                   stdout=subprocess.DEVNULL)
    subprocess.run([*CLI, "evaluate", str((out / "agent.py").relative_to(ROOT)), "--suite", suite, "--name", out.name,
                    "--out", str(results(algo, suite, seed).relative_to(ROOT)), "--overwrite"], check=True, env=env,
                   cwd=ROOT, stdout=subprocess.DEVNULL)
    write_results_section(out)


RESULTS_HEADING = "\n## Results (protocol 2, default seeds"


def results_section(folder: Path) -> str | None:
    """A learned run's README section stating its ranked results (None: it has none yet, or one still running)."""
    files = sorted(folder.glob("results-*.json"))
    done = [read_results(path) for path in files]
    if not files or not all(d.get("complete") for d in done):
        return None

    def ci(e: dict, fmt: str) -> str:
        return f"{e['mean']:{fmt}} [{e['low']:.4f}, {e['high']:.4f}]"

    rows = []
    for d in done:
        s = d["scores"]
        rows.append(f"| {d['suite']['name']} | {ci(s['mean'], '.4f')} | {s['curve'][0]['mean']:.3f} | "
                    f"{s['curve'][-1]['mean']:.3f} | {ci(s['adaptability'], '+.4f')} | "
                    f"{ci(s['comparisons']['best_fixed']['difference'], '+.4f')} | {len(d['seeds'])} |")
    offline = "dataset" in json.loads((folder / "run.json").read_text()).get("settings", {})
    curve = ("`metrics.csv` (the loss and accuracy of its predictions of the dataset's labels)" if offline
             else "`training_curve.png` (meta-train episode-1 and episode-10 normalised returns)")
    return (f"{RESULTS_HEADING}; `{files[0].name}`)\n\n"
            "| suite | mean score | s_1 | s_10 | adaptability | vs best fixed | seeds |\n"
            "|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n\n"
            f"Training: {curve}. How these compare with the paper's learned baselines: `docs/baselines.md`.\n")


def write_results_section(folder: Path) -> bool:
    """Put (or replace) the results section at the end of a learned run's README; whether it changed."""
    section = results_section(folder)
    readme = folder / "README.md"
    if section is None or not readme.exists():
        return False
    text = readme.read_text()
    kept = text.split(RESULTS_HEADING, 1)[0].rstrip() + "\n"
    if kept + section == text:
        return False
    readme.write_text(kept + section)
    return True


def learned_runs() -> list[Path]:
    """Every shipped run that `mewa-bench train` wrote (its folder has run.json)."""
    return sorted(p.parent for p in (ROOT / "submissions").glob("*/run.json"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=["status", "run", "readmes"])
    parser.add_argument("--suite", action="append", choices=list(SEEDS))
    parser.add_argument("--algo", action="append", choices=list(ALGOS))
    args = parser.parse_args()
    if args.what == "readmes":
        for folder in learned_runs():
            if write_results_section(folder):
                print(f"updated {folder.relative_to(ROOT)}/README.md")
        return
    runs = plan(args.suite or list(SEEDS), args.algo or list(ALGOS))
    if args.what == "status":
        for state in ("shipped", "missing", "other settings", "untuned"):
            mine = [f"{a}-{s}-seed{n}" for s, a, n, st in runs if st == state]
            print(f"{state} ({len(mine)}): {', '.join(mine) or '-'}")
        return
    for suite, algo, seed, state in runs:
        if state == "missing":
            print(f"{algo} on {suite}, seed {seed}", flush=True)
            run_one(algo, suite, seed)


if __name__ == "__main__":
    main()
