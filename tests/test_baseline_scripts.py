"""The scripts that train the shipped baselines: the tuning rule, and the runs planned from its selection."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import train_baselines  # noqa: E402
import tune_baselines  # noqa: E402


def row(suite: str, algo: str, config: str, mean: float) -> dict:
    return {"suite": suite, "algorithm": algo, "config": config, "validation_mean": f"{mean:.4f}"}


def test_a_variant_replaces_the_defaults_only_beyond_the_margin() -> None:
    rows = [row("narrow-v2", "rl2", "default", 0.70), row("narrow-v2", "rl2", "ent-0.1x", 0.709),
            row("narrow-v2", "maml", "default", 0.70), row("narrow-v2", "maml", "lr-0.3x", 0.7101),
            row("narrow-v2", "maml", "ent-0.1x", 0.72), row("wide-v2", "pearl", "kl-10x", 0.9)]
    chosen = tune_baselines.selection(rows)
    assert chosen == {("narrow-v2", "rl2"): "default", ("narrow-v2", "maml"): "ent-0.1x"}  # no defaults: no choice


def test_the_runs_use_the_selected_settings_and_untuned_suites_get_none() -> None:
    assert train_baselines.selected_settings("narrow-v1", "rl2") == {}
    assert train_baselines.selected_settings("narrow-v2", "rl2") == {"ent_coef": 0.001}  # docs/tuning.csv's choice
    assert train_baselines.selected_settings("narrow-v2", "varibad") == {}
    assert train_baselines.selected_settings("wide-v2", "rl2") == {"ent_coef": 0.001}
    assert train_baselines.selected_settings("wide-v2", "varibad") == {"ent_coef": 0.001}
    assert train_baselines.selected_settings("wide-v2", "pearl") == train_baselines.selected_settings("wide-v2", "maml") == {}
    assert train_baselines.same_settings({"ent_coef": "0.001"}, {"ent_coef": 0.001})
    assert not train_baselines.same_settings({}, {"ent_coef": 0.001})
    states = {(s, a, n): st for s, a, n, st in train_baselines.plan(["narrow-v1", "narrow-v2"], ["rl2", "maml"])}
    assert len(states) == 2 * 2 * 5
    assert all(states[("narrow-v1", a, n)] == "shipped" for a in ("rl2", "maml") for n in range(1, 6))
    assert all(st in ("shipped", "missing") for st in states.values())


def test_the_protocols_64_runs_are_shipped_with_the_selected_settings() -> None:
    """5 training seeds per algorithm on the narrow suites, 3 on the wide ones, each trained with the settings the
    tuning selected (a run of the defaults where a variant was selected would be "other settings")."""
    runs = train_baselines.plan(list(train_baselines.SEEDS), list(train_baselines.ALGOS))
    assert len(runs) == 4 * (5 + 3 + 5 + 3)
    assert [f"{a}-{s}-seed{n}: {state}" for s, a, n, state in runs if state != "shipped"] == []


def test_every_learned_runs_readme_states_its_results_files_numbers() -> None:
    """A shipped run's README ends with its results (`train_baselines.py readmes`): re-evaluating a run without
    rewriting its README, or editing the numbers by hand, fails here."""
    runs = train_baselines.learned_runs()
    assert len(runs) >= 50
    for folder in runs:
        section = train_baselines.results_section(folder)
        assert section is not None, f"{folder.name}: trained but not evaluated (no complete results-*.json)"
        readme = (folder / "README.md").read_text()
        assert readme.endswith(section), f"{folder.name}/README.md: its results section is not its results file's " \
                                         "(python scripts/train_baselines.py readmes)"
        assert readme.count(train_baselines.RESULTS_HEADING) == 1, folder.name


def test_the_results_section_is_replaced_not_appended_twice(tmp_path) -> None:
    import shutil

    folder = tmp_path / "maml-narrow-v1-seed1"
    shutil.copytree(train_baselines.ROOT / "submissions" / folder.name, folder,
                    ignore=shutil.ignore_patterns("checkpoint.pt", "*.png"))
    readme = folder / "README.md"
    before = readme.read_text()
    assert not train_baselines.write_results_section(folder)  # already current
    readme.write_text(before.replace("| 256 |", "| 255 |"))
    assert train_baselines.write_results_section(folder) and readme.read_text() == before
    readme.write_text(before.split(train_baselines.RESULTS_HEADING)[0])
    assert train_baselines.write_results_section(folder) and readme.read_text() == before
