"""Schema-3 results files: units as compressed typed columns, exact, reproducible, refused when tampered with."""

from __future__ import annotations

import base64
import json
import lzma
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mewa_bench.cli import app
from mewa_bench.design.suites import load_suite
from mewa_bench.files import json_text
from mewa_bench.leaderboard.validate import InvalidResults, SuiteCache, load_entry
from mewa_bench.protocol.config import EvalConfig, env_seed
from mewa_bench.protocol.results import (ResultsError, finish, read_results, results_text, stable_view, unit_key,
                                         write_results)
from mewa_bench.protocol.results_convert import convert_results
from mewa_bench.protocol.runner import evaluate
from mewa_bench.protocol.unit_columns import FILTERS, same_units

SUBMISSIONS = Path(__file__).resolve().parents[1] / "submissions"
WIDEST = SUBMISSIONS / "random-task-specific" / "results-wide-v1.json"  # 7,680 units of the noisiest returns
RANDOM = SUBMISSIONS / "random"
MB = 1_000_000


def as_schema(results: dict, schema: int) -> dict:
    return {**results, "schema_version": schema}


def test_a_shipped_wide_run_round_trips_exactly_in_under_a_megabyte(tmp_path: Path) -> None:
    old = read_results(WIDEST)
    assert len(old["units"]) == 7680
    path = tmp_path / "results.json"
    write_results(path, as_schema(old, 3))
    on_disk = json.loads(path.read_text())
    assert on_disk["schema_version"] == 3 and on_disk["units"]["derived"] == ["env_seeds"]
    assert sorted(on_disk["units"]["columns"]) == ["lengths", "normalised_returns", "pair", "returns", "scores",
                                                   "seed", "task"]
    assert path.stat().st_size <= MB, path.stat().st_size
    back = read_results(path)
    assert same_units(sorted(old["units"], key=unit_key), back["units"]) is None  # floats bit for bit
    assert back["units"] == sorted(old["units"], key=unit_key)
    assert as_schema(back, old["schema_version"]) == {**old, "units": back["units"]}  # every other field as it was
    write_results(tmp_path / "again.json", back)
    assert (tmp_path / "again.json").read_bytes() == path.read_bytes()  # the same results, the same bytes


def test_every_shipped_results_file_is_compact_and_at_most_a_megabyte() -> None:
    shipped = sorted(SUBMISSIONS.glob("*/results-*.json"))
    assert len(shipped) >= 20
    heavy = [f"{p.relative_to(SUBMISSIONS)}: {p.stat().st_size:,} bytes" for p in shipped if p.stat().st_size > MB]
    assert heavy == [], "rewrite them: mewa-bench results convert FILE (see the README)"
    for path in shipped:
        assert json.loads(path.read_text())["schema_version"] == 3, f"{path}: not in the compact schema-3 layout"


def rescored_copy(folder: Path, seeds: int | None = None) -> Path:
    """The shipped random agent's narrow-v1 run (cut to `seeds` seeds), scored by this version, as a schema-2 file
    in a submission folder of its own."""
    results = read_results(RANDOM / "results-narrow-v1.json")
    if seeds is not None:
        results["units"] = [u for u in results["units"] if u["seed"] < seeds]
        results["seeds"] = list(range(seeds))
    finish(results, load_suite("narrow-v1"))
    folder.mkdir(parents=True)
    for name in ("agent.py", "README.md"):
        shutil.copy(RANDOM / name, folder / name)
    path = folder / "results-narrow-v1.json"
    write_results(path, as_schema(results, 2))
    return path


def test_convert_rewrites_a_shipped_run_exactly_and_the_leaderboard_ranks_it_the_same(tmp_path: Path) -> None:
    path = rescored_copy(tmp_path / "a" / "random")
    twin = tmp_path / "b" / "random"
    shutil.copytree(path.parent, twin)
    old, before = read_results(path), load_entry(path, SuiteCache())
    assert old["schema_version"] == 2 and path.stat().st_size > 3 * MB
    result = CliRunner().invoke(app, ["results", "convert", str(path), str(twin / path.name)])
    assert result.exit_code == 0, result.output
    assert "schema 2 -> 3" in result.output
    new = read_results(path)
    assert new["schema_version"] == 3 and path.stat().st_size <= MB
    assert same_units(old["units"], new["units"]) is None
    assert json_text(new["scores"]) == json_text(old["scores"])
    after = load_entry(path, SuiteCache())
    assert json_text(after.scores.to_dict()) == json_text(before.scores.to_dict()) and after.seeds == before.seeds
    assert (twin / path.name).read_bytes() == path.read_bytes()  # converted twice, byte for byte the same
    again = convert_results(path)
    assert again.schema_before == 3 and (twin / path.name).read_bytes() == path.read_bytes()
    raw = json.loads(path.read_text())
    raw["units"]["predictors"]["max_expected"][0] *= 1.5  # pair 0's scores now decode a third lower
    path.write_text(json_text(raw))
    with pytest.raises(InvalidResults, match=r"unit \(pair 0, seed \d+\) episode \d+: score is not normalised return"):
        load_entry(path, SuiteCache())


def test_convert_refuses_a_file_that_does_not_check_out_and_leaves_it_alone(tmp_path: Path) -> None:
    path = rescored_copy(tmp_path / "random", seeds=3)
    good = read_results(path)

    def refused(change, message: str) -> None:
        results = json.loads(json.dumps(good))
        change(results)
        write_results(path, results)
        text = path.read_bytes()
        with pytest.raises(ResultsError, match=message):
            convert_results(path)
        assert path.read_bytes() == text

    refused(lambda r: r["units"][4]["env_seeds"].__setitem__(2, 12345), r"unit \(pair 1, seed 1\): env seeds are not")
    refused(lambda r: r["units"][0]["scores"].__setitem__(0, r["units"][0]["scores"][0] + 1e-15),
            r"unit \(pair 0, seed 0\): scores .* are not its normalised returns")
    refused(lambda r: r["scores"]["mean"].__setitem__("mean", r["scores"]["mean"]["mean"] + 1e-12),
            r"scores\.mean\.mean recomputed from the units differs from the stored one")
    refused(lambda r: r["units"][1].__setitem__("task", 3), r"unit \(pair 0, seed 1\): task 3 is not the pair's task")
    stale = json.loads(json.dumps(good))
    stale["scores"]["mean"]["mean"] += 1e-12  # as if scored by another version: only a re-score converts it
    write_results(path, stale)
    done = convert_results(path, rescore=True)
    assert done.rescored == ("scores.mean.mean",) and 0 < done.largest_change < 1e-11
    new = read_results(path)
    assert new["schema_version"] == 3 and same_units(good["units"], new["units"]) is None
    assert json_text(new["scores"]) == json_text(good["scores"])  # today's scores of the same units
    protocol1 = tmp_path / "protocol1.json"
    shutil.copy(Path(__file__).parent / "data" / "results-protocol1-random-narrow-v1.json", protocol1)
    with pytest.raises(ResultsError, match="schema 1 .* cannot become schema 3"):
        convert_results(protocol1)


def small_file(tmp_path: Path) -> Path:
    """A schema-3 file of 12 shipped units: pairs 0-5, seeds 0 and 1."""
    results = read_results(RANDOM / "results-narrow-v1.json")
    path = tmp_path / "small.json"
    write_results(path, {**as_schema(results, 3), "units": [u for u in results["units"] if u["seed"] < 2][:12]})
    return path


def xz(data: bytes) -> str:
    return base64.b64encode(lzma.compress(data, format=lzma.FORMAT_XZ, filters=FILTERS)).decode()


def _flip(text: str) -> str:
    middle = len(text) // 2
    return text[:middle] + ("A" if text[middle] != "A" else "B") + text[middle + 1:]


TAMPERED = [
    ("corrupt stream", lambda u: u["columns"]["returns"].update(xz_base64=_flip(u["columns"]["returns"]["xz_base64"])),
     r"units column returns: .*damaged or edited"),
    ("not base64", lambda u: u["columns"]["lengths"].update(xz_base64="not base64!"),
     "units column lengths: xz_base64 is not base64 text"),
    ("short column", lambda u: u["columns"]["returns"].update(xz_base64=xz(np.zeros(110, "<f8").tobytes())),
     r"units column returns: decompresses to 880 bytes, not the 960 bytes"),
    ("long column", lambda u: u["columns"]["seed"].update(xz_base64=xz(np.zeros(13, "<i8").tobytes())),
     r"units column seed: decompresses to more than the 96 bytes"),
    ("cut stream", lambda u: u["columns"]["pair"].update(
        xz_base64=base64.b64encode(base64.b64decode(u["columns"]["pair"]["xz_base64"])[:-20]).decode()),
     r"units column pair: .*(cut short|damaged or edited)"),
    ("data after", lambda u: u["columns"]["task"].update(
        xz_base64=base64.b64encode(base64.b64decode(u["columns"]["task"]["xz_base64"]) + b"\0\0\0\0").decode()),
     r"units column task: .*damaged or edited"),
    ("dtype", lambda u: u["columns"]["returns"].update(dtype="<f4"), r"units column returns: dtype '<f4'"),
    ("shape", lambda u: u["columns"]["lengths"].update(shape=[12, 9]), r"units column lengths: shape \[12, 9\]"),
    ("count", lambda u: u.update(count=13), r"units column pair: shape \[12\], expected \[13\]"),
    ("missing", lambda u: u["columns"].pop("scores"), "units column scores is missing"),
    ("stored and derived", lambda u: u["columns"].update(env_seeds=u["columns"]["seed"]),
     r"units column env_seeds is not a column of schema 3 \(its values are derived"),
    ("non-finite", lambda u: u["columns"]["returns"].update(xz_base64=xz(np.full(120, np.inf, "<f8").tobytes())),
     "units column returns: unit 0 holds a non-finite value"),
    ("pair beyond predictors", lambda u: u["predictors"].update(max_expected=[1.0]),
     r"units column pair: unit 2 has pair 1, units.predictors.max_expected covers 0..0"),
    ("count not a number", lambda u: u.update(count="12"), "units.count must be a whole number"),
]


@pytest.mark.parametrize("name,change,message", TAMPERED, ids=[t[0] for t in TAMPERED])
def test_tampered_or_malformed_columns_are_refused_naming_the_file_and_column(tmp_path: Path, name, change,
                                                                               message) -> None:
    path = small_file(tmp_path)
    raw = json.loads(path.read_text())
    change(raw["units"])
    path.write_text(json_text(raw))
    with pytest.raises(ResultsError, match=f"{path}: {message}"):
        read_results(path)


def unit(suite, pair: int, seed: int, returns: list[float]) -> dict:
    """A unit as the runner records one, for made-up returns."""
    from mewa_bench.game.normalise import episode_score, normalised_return

    p = suite.pairs[pair]
    normalised = [float(normalised_return(suite.tasks[p.task_index], r)) for r in returns]
    return {"pair": pair, "seed": seed, "task": p.task_index,
            "env_seeds": [env_seed(suite.sha256, pair, seed, k) for k in range(len(returns))], "returns": returns,
            "normalised_returns": normalised, "lengths": [k + 1 for k in range(len(returns))],
            "scores": [float(episode_score(v, p.max_expected)) for v in normalised]}


@pytest.mark.parametrize("suite_name", ["narrow-v1", "my-own-suite"])
def test_any_values_round_trip_bit_for_bit(tmp_path: Path, suite_name: str) -> None:
    suite = load_suite("narrow-v1")
    odd = [-0.0, 0.0, 5e-324, -1.7976931348623157e308, 0.1 + 0.2, -100.0, 1e-300, 2.5, -7.75, 3.0]
    units = [unit(suite, 0, 0, [-float(k) for k in range(10)]), unit(suite, 1, 0, [-0.5 * k for k in range(10)]),
             unit(suite, 2, 5, [-3.0] * 10)]
    units[1]["normalised_returns"] = odd  # not the returns' (residuals not zero), and every kind of float
    units[1]["scores"] = odd[::-1]
    units[2]["env_seeds"][3] = 2**64 - 1  # not the protocol's: the column is stored
    results = {"schema_version": 3, "protocol_version": 2, "complete": False, "agent": {"name": "x"},
               "suite": {"name": suite_name, "sha256": suite.sha256}, "env": {}, "package_version": "0",
               "seeds": [0, 5], "episodes_per_pair": 10, "units": units}
    path = tmp_path / "odd.json"
    write_results(path, results)
    packed = json.loads(path.read_text())["units"]
    assert packed["derived"] == [] and "env_seeds" in packed["columns"]
    assert (packed["predictors"] == {}) == (suite_name == "my-own-suite")  # only a shipped suite's are known
    back = read_results(path)
    assert same_units(units, back["units"]) is None
    assert str(back["units"][1]["normalised_returns"][0]) == "-0.0"
    assert results_text(back) == path.read_text()


def test_values_a_column_cannot_hold_exactly_are_refused_when_writing(tmp_path: Path) -> None:
    suite = load_suite("narrow-v1")
    base = {"schema_version": 3, "protocol_version": 2, "complete": False, "agent": {}, "env": {},
            "suite": {"name": "narrow-v1", "sha256": suite.sha256}, "package_version": "0", "seeds": [0],
            "episodes_per_pair": 10}
    whole = unit(suite, 0, 0, [-1.0] * 10)
    whole["returns"] = [-1] * 10  # an int would come back as a float
    with pytest.raises(ResultsError, match=r"units\[0\] \(pair 0, seed 0\) returns must be a list of 10 floats"):
        write_results(tmp_path / "r.json", {**base, "units": [whole]})
    nan = unit(suite, 0, 0, [-1.0] * 10)
    nan["returns"][4] = float("nan")
    with pytest.raises(ResultsError, match=r"returns holds a non-finite value"):
        write_results(tmp_path / "r.json", {**base, "units": [nan]})
    extra = {**unit(suite, 0, 0, [-1.0] * 10), "note": "hi"}
    with pytest.raises(ResultsError, match=r"units\[0\] must have exactly the fields"):
        write_results(tmp_path / "r.json", {**base, "units": [extra]})
    assert not (tmp_path / "r.json").exists()


def small_run(tmp_path: Path, name: str, **kw) -> EvalConfig:
    """The random agent in-process on seeds 0 and 1 of narrow-v1 (pairs 0-2 unless `pairs` is given)."""
    return EvalConfig(**{"agent_path": RANDOM / "agent.py", "out": tmp_path / name, "seeds": (0, 1),
                         "pairs": (0, 1, 2), "isolated": False, **kw})


@pytest.mark.parametrize("schema", [3, 2])
def test_a_run_resumes_from_a_partial_file_and_writes_schema_3(tmp_path: Path, schema: int) -> None:
    full, path = evaluate(small_run(tmp_path, "full.json"))
    assert json.loads(path.read_text())["schema_version"] == 3
    partial = {k: v for k, v in read_results(path).items() if k not in ("scores", "baselines")}
    partial.update(units=partial["units"][:4], complete=False, schema_version=schema)
    write_results(tmp_path / "part.json", partial)
    assert isinstance(json.loads((tmp_path / "part.json").read_text())["units"], dict if schema == 3 else list)
    resumed, out = evaluate(replace(small_run(tmp_path, "part.json"), resume=True))
    assert stable_view(resumed) == stable_view(full) and resumed["schema_version"] == 3
    assert same_units(read_results(out)["units"], full["units"]) is None
    assert json.loads(out.read_text())["units"]["count"] == 6


def test_the_service_takes_a_schema_3_upload_as_the_same_run_as_its_schema_2_twin(tmp_path: Path) -> None:
    from mewa_bench.service.errors import ApiError
    from mewa_bench.service.scoring import score_upload
    from mewa_bench.service.settings import Settings
    from mewa_bench.service.uploads import check_results

    full, _ = evaluate(small_run(tmp_path, "run.json", pairs=None))
    settings = Settings(data_dir=tmp_path / "data", seeds=2)
    schema3 = (tmp_path / "run.json").read_bytes()
    schema2 = json_text(as_schema(full, 2)).encode()
    three, two = check_results(schema3, settings, SuiteCache()), check_results(schema2, settings, SuiteCache())
    assert three.digest == two.digest  # the same episodes: one run, whichever layout carries them
    assert same_units(three.results["units"], two.results["units"]) is None
    scored = [score_upload(json.loads(data), (0, 1), 1) for data in (schema3, schema2)]
    assert scored[0].scores == scored[1].scores == json_text(full["scores"])
    raw = json.loads(schema3)
    raw["units"]["columns"]["lengths"]["shape"] = [1, 10]
    with pytest.raises(ApiError, match=r"results file: units column lengths: shape \[1, 10\]"):
        check_results(json_text(raw).encode(), settings, SuiteCache())
