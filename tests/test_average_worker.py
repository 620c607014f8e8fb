"""Eq. 1 (average worker and rewards): objective, solver, (delta, epsilon) search, scaling."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from mewa_bench.design import average_worker as aw
from mewa_bench.design.average_worker import (
    DELTAS,
    EPSILONS,
    AverageWorkerDesign,
    CandidateResult,
    design_average_worker,
    eq1_objective,
    eq1_terms,
    select_candidate,
    solve_eq1,
)

TOL = 1e-12


def toy_mad(w: np.ndarray, r: np.ndarray) -> float:
    """Stand-in scorer: the mean absolute deviation of the vector (1 - w, r / r_0)."""
    v = np.concatenate((1.0 - w, r / r[0]))
    return float(np.mean(np.abs(v - v.mean())))


@pytest.fixture(scope="module")
def designs() -> dict[tuple[int, int], AverageWorkerDesign]:
    """The full (delta, epsilon) search for every (N, M) the wide suites use, with the toy scorer."""
    return {(N, M): design_average_worker(N, M, toy_mad) for N in (3, 4) for M in (3, 4, 5)}


# --- the objective, by hand ---------------------------------------------------------------


def test_objective_by_hand_n2() -> None:
    # w = (0.5, 0.2), M = 3: d = (4, 1.75). Defined (x, y): (0,0), (1,1).
    # c[0,0,0] = 4 * -1 = -4,       c[0,1,1] = 2.75 * -1 - r_1 = -2.35
    # c[1,0,0] = 4 * -0.4 = -1.6,   c[1,1,1] = 2.75 * -0.4 = -1.1
    # f1 = 1.65^2 + 0.5^2 = 2.9725; f2 = (c[1,1,1] - d_1 r_0)^2 = 0.65^2 = 0.4225
    f1, f2 = eq1_terms(np.array([0.5, 0.2]), np.array([-1.0, -0.4]), 3)
    assert f1 == pytest.approx(2.9725, abs=TOL)
    assert f2 == pytest.approx(0.4225, abs=TOL)
    assert eq1_objective(np.array([0.5, 0.2]), np.array([-1.0, -0.4]), 3) == pytest.approx(3.395, abs=TOL)


def n3_by_hand(d: tuple[float, float, float], r: tuple[float, float, float]) -> tuple[float, float]:
    """f1, f2 for N = 3 with every c[j,x,y] written out from the formula (sum bounds done by hand)."""
    d0, d1, d2 = d
    r0, r1, r2 = r
    # Rows in the order (x, y) = (0,0), (1,0), (1,1), (2,1), (2,2); (2,0) is undefined (2 > 0 + 1).
    rows = [
        [d0 * r0, d1 * r0, (d1 + 1) * r0 - r1, (d2 + 1) * r0 - r2, (d2 + 2) * r0 - r1 - r2],
        [d0 * r1, d1 * r1, (d1 + 1) * r1 - r2, (d2 + 1) * r1, (d2 + 2) * r1 - r2],
        [d0 * r2, d1 * r2, (d1 + 1) * r2, (d2 + 1) * r2, (d2 + 2) * r2],
    ]
    f1 = sum((row[t + 1] - row[t]) ** 2 for row in rows for t in range(4))
    c11 = {(1, 1): rows[1][2], (1, 2): rows[1][4], (2, 1): rows[2][2], (2, 2): rows[2][4]}  # c[j,x,x]
    f2 = (
        (c11[1, 1] - d1 * r0) ** 2 + (c11[1, 2] - d2 * r0) ** 2  # j = 1, y = 0, x = 1..2
        + (c11[2, 2] - d2 * r0) ** 2  # j = 2, y = 0, x = 2
        + (c11[2, 1] - d1 * r1) ** 2 + (c11[2, 2] - d2 * r1) ** 2  # j = 2, y = 1, x = 1..2
    )
    return f1, f2


def test_objective_by_hand_n3_exact_fractions() -> None:
    # w = (0.5, 0.2, 0), M = 3: d = (4, 7/4, 1); r = (-1, -1/2, -1/4).
    # Worked on paper: f1 = 93/16 + 45/32 + 61/128 = 985/128, f2 = 157/256.
    w, r = np.array([0.5, 0.2, 0.0]), np.array([-1.0, -0.5, -0.25])
    f1, f2 = eq1_terms(w, r, 3)
    assert f1 == pytest.approx(985 / 128, abs=TOL)
    assert f2 == pytest.approx(157 / 256, abs=TOL)
    assert n3_by_hand((4.0, 1.75, 1.0), (-1.0, -0.5, -0.25)) == pytest.approx((985 / 128, 157 / 256), abs=TOL)


def test_objective_by_hand_n3_generic_numbers() -> None:
    w, r, M = np.array([0.61, 0.37, 0.12]), np.array([-0.9, -0.55, -0.07]), 5
    d = tuple((1 + (M - 1) * wx) / (1 - wx) for wx in w)
    assert eq1_terms(w, r, M) == pytest.approx(n3_by_hand(d, tuple(r)), rel=1e-13)


def test_objective_is_homogeneous_of_degree_two_in_r() -> None:
    w, r = np.array([0.7, 0.5, 0.3, 0.1]), np.array([-1.0, -0.6, -0.3, -0.1])
    assert eq1_objective(w, 0.1 * r, 4) == pytest.approx(0.01 * eq1_objective(w, r, 4), rel=1e-12)


def test_objective_rejects_mismatched_vectors() -> None:
    with pytest.raises(ValueError):
        eq1_terms(np.array([0.5, 0.2, 0.1]), np.array([-1.0, -0.5]), 3)


@pytest.mark.parametrize("N", [2, 3, 4])
def test_gradient_matches_central_differences(N: int) -> None:
    s = aw.eq1_structure(N)
    rng = np.random.default_rng(7)
    for M in (2, 3, 5):
        z = np.concatenate((np.sort(rng.uniform(0.05, 0.9, N))[::-1], np.sort(rng.uniform(-0.95, -0.05, N - 1))))
        value, grad = aw.objective_and_gradient(z, s, M)
        assert value == pytest.approx(eq1_objective(z[:N], np.concatenate(([-1.0], z[N:])), M), rel=1e-14)
        h = 1e-6
        numeric = np.array([
            (aw.objective_and_gradient(z + h * e, s, M)[0] - aw.objective_and_gradient(z - h * e, s, M)[0]) / (2 * h)
            for e in np.eye(len(z))
        ])
        assert grad == pytest.approx(numeric, rel=1e-6, abs=1e-6 * max(1.0, value))


# --- the solver ---------------------------------------------------------------------------


def assert_feasible(w: tuple[float, ...], r: tuple[float, ...], delta: float, epsilon: float) -> None:
    """Every constraint of Eq. 1, checked directly (up to the 12-decimal output rounding)."""
    N = len(w)
    assert len(r) == N
    assert all(0.0 <= wx <= 1.0 - 1e-6 + TOL for wx in w)
    assert all(w[x] - w[x + 1] >= delta - TOL for x in range(N - 1))
    assert w[N - 1] >= epsilon - TOL
    assert all(r[i + 1] - r[i] >= 1e-6 - TOL for i in range(N - 1))
    assert r[N - 1] <= -1e-6 + TOL
    assert -1.0 <= r[0] < -0.1


@pytest.mark.parametrize("N, M", list(itertools.product((3, 4), (3, 4, 5))))
def test_every_candidate_is_feasible(designs, N: int, M: int) -> None:
    design = designs[N, M]
    assert design.candidates
    for cand in design.candidates:
        assert_feasible(cand.w, cand.r, cand.delta, cand.epsilon)
        assert cand.r[0] == -1.0  # r_0 = -1 fixes the scale and needs no power-of-ten rescaling
        assert cand.objective == pytest.approx(eq1_objective(np.array(cand.w), np.array(cand.r), M), rel=1e-11)
    assert_feasible(design.w, design.r, design.delta, design.epsilon)


def random_feasible_neighbours(
    w: np.ndarray, r: np.ndarray, delta: float, epsilon: float, rng: np.random.Generator, step: float, count: int
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Random nearby points of the feasible set (r_0 stays -1): perturb, then push back inside.

    Each coordinate is first clipped to the range the chained constraints leave it, so pushing
    w_x up to w_{x+1} + delta (r_i up to r_{i-1} + 1e-6) can never cross an upper bound.
    """
    N, m = len(w), 1e-6
    out = []
    for _ in range(count):
        w2 = w + step * rng.standard_normal(N)
        r2 = r + step * np.concatenate(([0.0], rng.standard_normal(N - 1)))
        for x in range(N - 1, -1, -1):
            w2[x] = np.clip(w2[x], epsilon + (N - 1 - x) * delta, 1.0 - m - x * delta)
            if x < N - 1:
                w2[x] = max(w2[x], w2[x + 1] + delta)
        for i in range(1, N):
            r2[i] = max(np.clip(r2[i], -1.0 + i * m, -(N - i) * m), r2[i - 1] + m)
        out.append((w2, r2))
    return out


@pytest.mark.parametrize("N, M", list(itertools.product((3, 4), (3, 4, 5))))
def test_solutions_are_local_minima(designs, N: int, M: int) -> None:
    rng = np.random.default_rng(12345)
    for cand in designs[N, M].candidates:
        w, r = np.array(cand.w), np.array(cand.r)
        best = eq1_objective(w, r, M)
        tolerance = 1e-9 * max(1.0, best)
        for step in (1e-2, 1e-4, 1e-6):
            neighbours = random_feasible_neighbours(w, r, cand.delta, cand.epsilon, rng, step, 40)
            for w2, r2 in neighbours:
                assert_feasible(tuple(w2), tuple(r2), cand.delta, cand.epsilon)
            worst_gain = max(best - eq1_objective(w2, r2, M) for w2, r2 in neighbours)
            assert worst_gain <= tolerance, (cand.delta, cand.epsilon, step, worst_gain)


@pytest.mark.parametrize("N, M", list(itertools.product((3, 4), (3, 4, 5))))
def test_free_rewards_are_stationary(designs, N: int, M: int) -> None:
    # Where no r constraint binds, r must be the exact least-squares minimiser for its w (SLSQP
    # alone leaves gradients around 1e-7 f; exact solving leaves only the 12-decimal rounding).
    s = aw.eq1_structure(N)
    checked = 0
    for cand in designs[N, M].candidates:
        r = np.array(cand.r)
        if np.min(np.diff(r)) < 1e-5 or r[-1] > -1e-5:
            continue
        value, grad = aw.objective_and_gradient(np.concatenate((cand.w, r[1:])), s, M)
        assert np.max(np.abs(grad[N:])) <= 1e-9 * max(1.0, value), (cand.delta, cand.epsilon)
        checked += 1
    assert checked >= len(designs[N, M].candidates) // 2


def test_solution_is_no_worse_than_any_starting_point() -> None:
    N, M, delta, epsilon = 4, 3, 0.13125, 0.1125
    sol = solve_eq1(N, M, delta, epsilon)
    for z in aw.starting_points(N, delta, epsilon):
        assert_feasible(tuple(z[:N]), (-1.0, *z[N:]), delta, epsilon)
        assert sol.objective <= eq1_objective(z[:N], np.concatenate(([-1.0], z[N:])), M) + 1e-9


def test_solve_is_deterministic_and_ignores_the_global_rng() -> None:
    np.random.seed(1)
    first = solve_eq1(4, 3, 0.1875, 0.15)
    np.random.seed(2)
    np.random.random(1000)
    second = solve_eq1(4, 3, 0.1875, 0.15)
    assert first == second  # dataclass equality: every float identical


def test_design_is_deterministic_byte_for_byte() -> None:
    grid = {"deltas": (0.075, 0.3), "epsilons": (0.075, 0.225)}
    first = design_average_worker(3, 4, toy_mad, **grid).to_dict()
    second = design_average_worker(3, 4, toy_mad, **grid).to_dict()
    assert json.dumps(first, sort_keys=True) == json.dumps(second, sort_keys=True)


def test_outputs_are_rounded_to_twelve_decimals(designs) -> None:
    for design in designs.values():
        for cand in design.candidates:
            assert all(v == round(v, 12) for v in (*cand.w, *cand.r))


# --- the (delta, epsilon) search ----------------------------------------------------------


def test_infeasible_pairs_are_skipped_and_never_scored() -> None:
    seen: list[tuple[float, ...]] = []

    def recording_mad(w: np.ndarray, r: np.ndarray) -> float:
        seen.append(tuple(w))
        return toy_mad(w, r)

    # N = 4: epsilon + 3 delta > 1 exactly for delta = 0.3 with epsilon >= 0.1125.
    design = design_average_worker(4, 3, recording_mad, deltas=(0.24375, 0.3), epsilons=EPSILONS)
    expected_skipped = {(0.3, e) for e in (0.1125, 0.15, 0.1875, 0.225)}
    assert set(design.skipped) == expected_skipped
    assert {(c.delta, c.epsilon) for c in design.candidates} == {
        (d, e) for d in (0.24375, 0.3) for e in EPSILONS
    } - expected_skipped
    assert len(seen) == len(design.candidates) == 6
    assert seen == [c.w for c in design.candidates]
    with pytest.raises(ValueError, match="infeasible"):
        solve_eq1(4, 3, 0.3, 0.1125)


def test_full_grid_skips_exactly_the_infeasible_pairs(designs) -> None:
    for (N, _), design in designs.items():
        infeasible = {(d, e) for d in DELTAS for e in EPSILONS if e + (N - 1) * d > 1}
        assert set(design.skipped) == infeasible
        assert len(design.candidates) + len(design.skipped) == len(DELTAS) * len(EPSILONS)
    assert len(designs[4, 3].skipped) == 4 and not designs[3, 3].skipped


def test_no_feasible_pair_is_an_error() -> None:
    with pytest.raises(ValueError):
        design_average_worker(4, 3, toy_mad, deltas=(0.3,), epsilons=(0.225,))


@pytest.mark.parametrize("N, M", list(itertools.product((3, 4), (3, 4, 5))))
def test_selection_takes_the_smallest_mad(designs, N: int, M: int) -> None:
    design = designs[N, M]
    for cand in design.candidates:
        assert cand.mad == pytest.approx(toy_mad(np.array(cand.w), np.array(cand.r)), rel=1e-11)
    smallest = min(c.mad for c in design.candidates)
    first = next(c for c in design.candidates if c.mad == smallest)
    assert design.mad == smallest
    assert (design.delta, design.epsilon, design.w, design.r) == (first.delta, first.epsilon, first.w, first.r)
    assert design.objective == first.objective


def candidate(delta: float, epsilon: float, mad: float) -> CandidateResult:
    """A made-up candidate for the selection rule alone."""
    return CandidateResult(delta, epsilon, (0.5, 0.1), (-1.0, -0.5), 1.0, mad)


def test_selection_ties_break_by_grid_order_and_nan_never_wins() -> None:
    cands = [candidate(0.075, 0.075, math.nan), candidate(0.075, 0.15, 0.02), candidate(0.13125, 0.075, 0.01),
             candidate(0.13125, 0.15, 0.01 + 1e-15), candidate(0.3, 0.075, 0.01)]
    chosen = select_candidate(cands)
    assert (chosen.delta, chosen.epsilon) == (0.13125, 0.075)  # 12-decimal ties: the first one
    assert select_candidate(cands[::-1]).delta == 0.3  # order, not the numbers, breaks the tie
    assert select_candidate([cands[0]]).delta == 0.075  # a lone NaN is still returned
    with pytest.raises(ValueError):
        select_candidate([])


def test_selection_follows_the_scorer() -> None:
    # A scorer that prefers the worker whose smallest mistake rate is 0.15: the search must land there.
    grid = {"deltas": (0.075, 0.1875), "epsilons": (0.075, 0.15, 0.225)}
    design = design_average_worker(3, 3, lambda w, r: abs(float(w[-1]) - 0.15), **grid)
    assert design.w[-1] == pytest.approx(0.15, abs=1e-9)
    assert design.epsilon == 0.15
    assert design.delta == 0.075  # both deltas score 0 for epsilon = 0.15: the earlier one wins
    constant = design_average_worker(3, 3, lambda w, r: 0.5, **grid)
    assert (constant.delta, constant.epsilon) == (0.075, 0.075)


# --- scaling and serialisation ------------------------------------------------------------


def test_every_shipped_task_has_r0_minus_one() -> None:
    """SPEC section 4's power-of-ten rule (-1 <= r_0 < -0.1) holds because Eq. 1 fixes r_0 = -1."""
    from mewa_bench.design.suites import ALL_SUITES, load_suite

    assert {t.rewards[0] for name in ALL_SUITES for t in load_suite(name).tasks} == {-1.0}


def test_to_dict_is_plain_json(designs) -> None:
    design = designs[4, 3]
    data = design.to_dict()
    text = json.dumps(data, sort_keys=True, separators=(",", ":"))
    back = json.loads(text)
    assert back["w"] == list(design.w) and back["r"] == list(design.r)
    assert back["objective"] == design.objective and back["mad"] == design.mad
    assert (back["delta"], back["epsilon"], back["N"], back["M"]) == (design.delta, design.epsilon, 4, 3)
    assert len(back["candidates"]) == len(design.candidates)
    assert back["candidates"][0]["w"] == list(design.candidates[0].w)
    assert back["skipped"] == [list(p) for p in design.skipped]
