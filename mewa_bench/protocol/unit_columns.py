"""The compact form of a results file's units (schema 3): typed little-endian columns, xz, base64.

In a schema-3 file `units` is an object, not a list:

    {"count": N,
     "derived": ["env_seeds"],            # or [] when the env seeds are stored
     "predictors": {"low": [...], "span": [...], "max_expected": [...]},   # or {}
     "columns": {NAME: {"dtype": ..., "shape": [N] or [N, K], "xz_base64": ...}, ...}}

with K = `episodes_per_pair` and the columns, units in (pair, seed) order:

    pair, seed, task                          int64  [N]
    lengths                                   int64  [N, K]
    returns                                   float64 [N, K]
    normalised_returns, scores                float64 [N, K], or uint64 [N, K] residuals (below)
    env_seeds (only when not derived)         uint64 [N, K]

A column is its values' raw little-endian bytes, row-major, as one xz stream (LZMA2 with the fixed
settings of `FILTERS`, CRC64 check; xz stores no names or times), base64-encoded: the same units
always give the same bytes, and decoding gives back the same values bit for bit. `env_seeds` are
left out when every one is the protocol's `env_seed(suite hash, pair, seed, episode)`, the only
env seeds a ranked run may have; a reader derives them again.

Normalised returns and scores are functions of the returns (SPEC section 2), so on a shipped suite
they are stored as residuals: the XOR of their float64 bits with those of a prediction from the
`predictors` (the suite's per-task return bounds and per-pair max-expected baselines, copied into
the file so that a reader needs no suite):

    normalised_returns = bits((returns - low[task]) / span[task]) XOR residual
    scores             = bits(normalised_returns / max_expected[pair]) XOR residual

The residuals of a run are all zero (so they cost next to nothing), but any values round-trip
exactly. On other suites (hidden, or of your own) `predictors` is {} and both are plain float64.
"""

from __future__ import annotations

import base64
import binascii
import lzma
import math
from functools import lru_cache
from itertools import chain
from typing import Any, NamedTuple

import numpy as np

from mewa_bench.protocol.config import env_seed

INT, FLOAT, SEED, RESIDUAL = "<i8", "<f8", "<u8", "<u8"
UNIT_COLUMNS = ("pair", "seed", "task")  # one value per unit
EPISODE_COLUMNS = {"env_seeds": SEED, "returns": FLOAT, "normalised_returns": FLOAT, "lengths": INT, "scores": FLOAT}
DTYPES = {**{name: INT for name in UNIT_COLUMNS}, **EPISODE_COLUMNS}
FIELDS = tuple(DTYPES)  # the fields of a unit dict
DERIVABLE = "env_seeds"
PREDICTED = ("normalised_returns", "scores")
# 8-byte values: no literal context, positions aligned to 8 bytes; a 4 MiB window holds a column of 50,000 units.
# Preset 1: files 3-4% larger than with preset 6, written 5x faster (a run rewrites its file as units finish)
FILTERS = ({"id": lzma.FILTER_LZMA2, "preset": 1, "dict_size": 1 << 22, "lc": 0, "lp": 3, "pb": 3},)
# ten times the largest protocol run (256 seeds x 80 pairs): bounds what a small file can make a reader allocate
MAX_UNITS = 200_000
_KEYS = {"count", "derived", "predictors", "columns"}
_PREDICTORS = ("low", "span", "max_expected")
_COLUMN_KEYS = {"dtype", "shape", "xz_base64"}


class ColumnError(ValueError):
    """The units cannot be stored as columns, or a file's columns are malformed or were tampered with."""


class Predictors(NamedTuple):
    """Return bounds per task (low, span = high - low) and the max-expected baseline per pair."""

    low: tuple[float, ...]
    span: tuple[float, ...]
    max_expected: tuple[float, ...]


@lru_cache(maxsize=16)
def suite_predictors(name: str, sha256: str) -> Predictors | None:
    """The predictors of the shipped suite `name` if its hash is `sha256`; None for any other suite."""
    from mewa_bench.design.suites import ALL_SUITES, load_suite
    from mewa_bench.game.normalise import return_bounds

    if name not in ALL_SUITES:
        return None
    suite = load_suite(name)
    if suite.sha256 != sha256:
        return None
    bounds = [return_bounds(task) for task in suite.tasks]
    return Predictors(tuple(float(lo) for lo, _ in bounds), tuple(float(hi - lo) for lo, hi in bounds),
                      tuple(float(p.max_expected) for p in suite.pairs))


@lru_cache(maxsize=1 << 14)  # two ranked wide runs' units
def protocol_env_seeds(suite_hash: str, pair: int, seed: int, episodes: int) -> tuple[int, ...]:
    """The env seeds the protocol gives a unit's episodes (cached: a run's file is written many times)."""
    return tuple(env_seed(suite_hash, pair, seed, k) for k in range(episodes))


def encode_units(units: list[dict[str, Any]], episodes: int, suite: dict[str, Any], where: str) -> dict[str, Any]:
    """The `units` object of a schema-3 file for unit dicts (in the order given), on `suite` (a results file's
    name and sha256); ColumnError if a unit does not fit."""
    _check_units(units, episodes, where)
    arrays = {}
    for name in FIELDS:
        shape = (len(units),) if name in UNIT_COLUMNS else (len(units), episodes)
        try:
            arrays[name] = np.array([u[name] for u in units], dtype=DTYPES[name]).reshape(shape)
        except OverflowError:
            raise ColumnError(f"{where}: units column {name} holds a value outside the range of "
                              f"{np.dtype(DTYPES[name])}") from None
    for name in ("returns", *PREDICTED):
        if not np.isfinite(arrays[name]).all():
            u = int(np.argwhere(~np.isfinite(arrays[name]))[0][0])
            raise ColumnError(f"{where}: units[{u}] (pair {units[u]['pair']}, seed {units[u]['seed']}) {name} holds "
                              f"a non-finite value (results hold finite numbers only)")
    derived = all(tuple(u["env_seeds"]) == protocol_env_seeds(suite["sha256"], u["pair"], u["seed"], episodes)
                  for u in units)
    predictors = suite_predictors(suite["name"], suite["sha256"])
    if predictors is not None and not _covers(predictors, arrays["task"], arrays["pair"]):
        predictors = None  # units of tasks or pairs the suite does not have: stored as they are
    if predictors is not None:
        for name, prediction in zip(PREDICTED, _predictions(predictors, arrays)):
            arrays[name] = arrays[name].view(RESIDUAL) ^ prediction.view(RESIDUAL)
    columns = {name: _encode(array) for name, array in arrays.items() if not (derived and name == DERIVABLE)}
    return {"count": len(units), "derived": [DERIVABLE] if derived else [],
            "predictors": {} if predictors is None else {k: list(v) for k, v in predictors._asdict().items()},
            "columns": columns}


def decode_units(packed: Any, episodes: int, suite_hash: str, where: str) -> list[dict[str, Any]]:
    """The unit dicts of a schema-3 `units` object; ColumnError names the column that is malformed."""
    if not isinstance(packed, dict) or set(packed) != _KEYS:
        raise ColumnError(f"{where}: units must be an object with exactly {', '.join(sorted(_KEYS))} in schema 3, got "
                          f"{_shape_of(packed)}")
    count, derived, columns = packed["count"], packed["derived"], packed["columns"]
    predictors = _predictors(packed["predictors"], where)
    if not isinstance(count, int) or isinstance(count, bool) or not 0 <= count <= MAX_UNITS:
        raise ColumnError(f"{where}: units.count must be a whole number in 0..{MAX_UNITS}, got {count!r}")
    if derived not in ([], [DERIVABLE]):
        raise ColumnError(f"{where}: units.derived must be [] or [\"{DERIVABLE}\"], got {derived!r}")
    if not isinstance(columns, dict):
        raise ColumnError(f"{where}: units.columns must be an object, got {_shape_of(columns)}")
    expected = [name for name in FIELDS if not (derived and name == DERIVABLE)]
    missing = [name for name in expected if name not in columns]
    unexpected = sorted(str(name) for name in columns if name not in expected)
    if missing:
        raise ColumnError(f"{where}: units column {missing[0]} is missing")
    if unexpected:
        why = " (its values are derived: units.derived lists it)" if unexpected[0] == DERIVABLE else ""
        raise ColumnError(f"{where}: units column {unexpected[0]} is not a column of schema 3{why}")
    arrays = {name: _decode(name, columns[name], count, episodes, predictors is not None, where) for name in expected}
    if predictors is not None:
        for name, at in (("task", "low"), ("pair", "max_expected")):
            outside = np.flatnonzero((arrays[name] < 0) | (arrays[name] >= len(getattr(predictors, at))))
            if len(outside):
                raise ColumnError(f"{where}: units column {name}: unit {int(outside[0])} has {name} "
                                  f"{int(arrays[name][outside[0]])}, units.predictors.{at} covers "
                                  f"0..{len(getattr(predictors, at)) - 1}")
        for name, prediction in zip(PREDICTED, _predictions(predictors, arrays)):
            arrays[name] = (arrays[name] ^ prediction.view(RESIDUAL)).view(FLOAT)
    for name in PREDICTED:
        if not np.isfinite(arrays[name]).all():
            u = int(np.argwhere(~np.isfinite(arrays[name]))[0][0])
            raise ColumnError(f"{where}: units column {name}: unit {u} holds a non-finite value (results hold "
                              f"finite numbers only)")
    lists = {name: array.tolist() for name, array in arrays.items()}
    units = []
    for i in range(count):
        unit = {name: lists[name][i] for name in expected}
        if derived:
            unit[DERIVABLE] = list(protocol_env_seeds(suite_hash, unit["pair"], unit["seed"], episodes))
        units.append(unit)
    return units


def same_units(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> str | None:
    """None if two unit lists are identical (same fields, types, and floats bit for bit), else where they differ."""
    if len(a) != len(b):
        return f"{len(a)} units, then {len(b)}"
    for i, (x, y) in enumerate(zip(a, b)):
        if set(x) != set(y):
            return f"units[{i}] has fields {sorted(x)}, then {sorted(y)}"
        for name in x:
            if _bits(x[name]) != _bits(y[name]):
                return f"units[{i}] (pair {x.get('pair')}, seed {x.get('seed')}) {name}: {x[name]!r}, then {y[name]!r}"
    return None


def _bits(value: Any) -> Any:
    """A value with every float replaced by its type and bit pattern (so -0.0 differs from 0.0)."""
    if isinstance(value, list):
        return [_bits(v) for v in value]
    if isinstance(value, float):
        return ("float", np.float64(value).tobytes())
    return (type(value).__name__, value)


def _check_units(units: list[Any], episodes: int, where: str) -> None:
    """Unit dicts have exactly the unit fields, integers where the columns hold integers, floats in the float
    columns, `episodes` values per episode column (checked column by column: a run's file is written often)."""
    fields = set(FIELDS)
    bad = next((i for i, u in enumerate(units) if not isinstance(u, dict) or set(u) != fields), None)
    if bad is not None:
        got = sorted(units[bad]) if isinstance(units[bad], dict) else type(units[bad]).__name__
        raise ColumnError(f"{where}: units[{bad}] must have exactly the fields {', '.join(FIELDS)}, got {got}")
    for name in UNIT_COLUMNS:
        if not _all_of(INT, [u[name] for u in units]):
            i = next(i for i, u in enumerate(units) if not _all_of(INT, [u[name]]))
            raise ColumnError(f"{where}: units[{i}] {name} must be an integer, got {units[i][name]!r}")
    for name, dtype in EPISODE_COLUMNS.items():
        rows = [u[name] for u in units]
        i = next((i for i, row in enumerate(rows) if type(row) is not list or len(row) != episodes), None)
        if i is None and _all_of(dtype, list(chain.from_iterable(rows))):
            continue
        i = i if i is not None else next(i for i, row in enumerate(rows) if not _all_of(dtype, row))
        kind = "floats" if dtype == FLOAT else "integers"
        raise ColumnError(f"{where}: units[{i}] (pair {units[i]['pair']}, seed {units[i]['seed']}) {name} must be a "
                          f"list of {episodes} {kind}, got {rows[i]!r}")


def _all_of(dtype: str, values: list[Any]) -> bool:
    """Every value is a Python (or numpy) float for a float column, an integer (not a bool) otherwise."""
    types = set(map(type, values))
    if dtype == FLOAT:
        return all(issubclass(t, float) for t in types)
    return all(issubclass(t, int) and not issubclass(t, bool) for t in types)


def _covers(predictors: Predictors, task: np.ndarray, pair: np.ndarray) -> bool:
    """Every unit's task and pair has its predictor."""
    tasks_known = ((task >= 0) & (task < len(predictors.low))).all()
    return bool(tasks_known and ((pair >= 0) & (pair < len(predictors.max_expected))).all())


def _predictions(predictors: Predictors, arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The normalised returns and scores predicted from the returns (and the normalised returns, once known)."""
    low, span = np.array(predictors.low)[arrays["task"]], np.array(predictors.span)[arrays["task"]]
    with np.errstate(all="ignore"):  # a tampered table may divide by zero: the residual still round-trips
        normalised = (arrays["returns"] - low[:, None]) / span[:, None]
    # the scores are predicted from the stored normalised returns: decoded first, or as given when encoding
    stored = arrays["normalised_returns"]
    actual = stored if stored.dtype == np.dtype(FLOAT) else (stored ^ normalised.view(RESIDUAL)).view(FLOAT)
    with np.errstate(all="ignore"):
        scores = actual / np.array(predictors.max_expected)[arrays["pair"]][:, None]
    return normalised.astype(FLOAT), scores.astype(FLOAT)


def _predictors(table: Any, where: str) -> Predictors | None:
    """A file's predictors ({}: none), checked: lists of finite numbers, bounds for as many tasks as spans."""
    if table == {}:
        return None
    if not isinstance(table, dict) or set(table) != set(_PREDICTORS):
        raise ColumnError(f"{where}: units.predictors must be {{}} or an object with exactly {', '.join(_PREDICTORS)}, "
                          f"got {_shape_of(table)}")
    for key in _PREDICTORS:
        values = table[key]
        numbers = isinstance(values, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
        if not numbers or not 1 <= len(values) <= MAX_UNITS or not all(math.isfinite(v) for v in values):
            raise ColumnError(f"{where}: units.predictors.{key} must be a non-empty list of finite numbers")
    if len(table["low"]) != len(table["span"]):
        raise ColumnError(f"{where}: units.predictors: low has {len(table['low'])} tasks, span {len(table['span'])}")
    return Predictors(*(tuple(float(v) for v in table[key]) for key in _PREDICTORS))


def _encode(array: np.ndarray) -> dict[str, Any]:
    """One column: its values as little-endian bytes, xz-compressed, base64."""
    data = lzma.compress(array.tobytes(), format=lzma.FORMAT_XZ, check=lzma.CHECK_CRC64, filters=FILTERS)
    return {"dtype": array.dtype.str, "shape": list(array.shape), "xz_base64": base64.b64encode(data).decode("ascii")}


def _decode(name: str, column: Any, count: int, episodes: int, predicted: bool, where: str) -> np.ndarray:
    """One column back as an array; refuses a wrong dtype or shape, bad base64, a corrupt stream, a wrong length."""
    at = f"{where}: units column {name}"
    if not isinstance(column, dict) or set(column) != _COLUMN_KEYS:
        raise ColumnError(f"{at} must be an object with exactly {', '.join(sorted(_COLUMN_KEYS))}, got "
                          f"{_shape_of(column)}")
    dtype = RESIDUAL if predicted and name in PREDICTED else DTYPES[name]
    shape = [count] if name in UNIT_COLUMNS else [count, episodes]
    if column["dtype"] != dtype:
        form = " (a residual: units.predictors is not {})" if dtype == RESIDUAL and name in PREDICTED else ""
        raise ColumnError(f"{at}: dtype {column['dtype']!r}, schema 3 stores it as {dtype!r}{form}")
    if column["shape"] != shape:
        raise ColumnError(f"{at}: shape {column['shape']!r}, expected {shape} ({count} units x {episodes} episodes)")
    text = column["xz_base64"]
    try:
        if not isinstance(text, str):
            raise TypeError
        data = base64.b64decode(text.encode("ascii"), validate=True)
    except (binascii.Error, UnicodeEncodeError, TypeError):
        raise ColumnError(f"{at}: xz_base64 is not base64 text") from None
    size = int(np.prod(shape)) * 8
    decompressor = lzma.LZMADecompressor(format=lzma.FORMAT_XZ)
    try:
        raw = decompressor.decompress(data, max_length=size + 1)  # never more than the column can hold
    except lzma.LZMAError as e:
        raise ColumnError(f"{at}: the xz data is corrupt ({e}): the file was damaged or edited") from None
    if len(raw) > size:
        raise ColumnError(f"{at}: decompresses to more than the {size} bytes of shape {shape} in {dtype}: the file "
                          f"was damaged or edited")
    if not decompressor.eof:
        raise ColumnError(f"{at}: the xz stream is cut short: the file was damaged or edited")
    if decompressor.unused_data:
        raise ColumnError(f"{at}: there is data after its xz stream: the file was damaged or edited")
    if len(raw) != size:
        raise ColumnError(f"{at}: decompresses to {len(raw)} bytes, not the {size} bytes of shape {shape} in {dtype}: "
                          f"the file was damaged or edited")
    array = np.frombuffer(raw, dtype=dtype).reshape(shape)
    if dtype == FLOAT and not np.isfinite(array).all():
        u = int(np.argwhere(~np.isfinite(array))[0][0])
        raise ColumnError(f"{at}: unit {u} holds a non-finite value (results hold finite numbers only)")
    return array


def _shape_of(value: Any) -> str:
    """What a malformed value is, briefly."""
    if isinstance(value, dict):
        return "an object with " + (", ".join(sorted(map(str, value))) or "no fields")
    return type(value).__name__
