"""Average worker and step rewards of a task (SPEC section 4, Eq. 1).

For d_x = (1 + (M-1) w_x) / (1 - w_x) and every defined triple (j, x, y) -- j, x in 0..N-1,
y in 0..x, x <= y + N - 2 --

    c[j,x,y] = (d_x + y) r_j - sum_{k = x-y+j+1}^{min(x+j+1, N) - 1} r_k      (empty sum = 0)

    f1 = sum_j sum of (c[j,t+1] - c[j,t])^2 over the defined (x, y) of row j in x-major,
         y-minor order
    f2 = sum_{j=1}^{N-1} sum_{y=0}^{j-1} sum_{x=j-y}^{N-1} (c[j,x,x] - d_x r_y)^2

f1 + f2 is minimised over (w, r) with r_0 = -1 fixed (the objective is homogeneous of degree 2
in r), by SLSQP from a fixed set of starting points, for every feasible (delta, epsilon) of the
SPEC's grid; the solution whose t-optimal policies have the smallest MAD at w_avg is kept.
SLSQP minimises log(f1 + f2) (same minimisers): d_x grows like 1/(1 - w_x), so f1 + f2 spans
many orders of magnitude over the feasible set and an absolute ftol either stops too early or
never triggers; on the log scale the stopping rule is relative.

Index notes: in f2 the lower summation bound x-y+j+1 is always >= 1 and, with y = x, the
condition x <= x + N - 2 holds for every N >= 2, so every c[j,x,x] that f2 reads is defined; no
undefined combination ever occurs and none needs special handling.

Each SLSQP end point is polished: w is snapped onto the constraints it lies within 1e-7 of,
and r is re-solved exactly for that w (for a fixed w every residual is linear in r, so this is
a small equality-constrained least-squares problem, the r constraints active at the SLSQP point
being the equalities). The polished point is kept when it is feasible and no worse. Without
it r is only accurate to about 1e-9 and its 12th decimal would depend on the starting point.

Output conventions (suite files must be byte-reproducible): w and r are rounded to 12
decimals after a tiny repair step that re-imposes the linear constraints exactly; the recorded
objective is f1 + f2 at the rounded (w, r), rounded to 12 significant digits, as is the MAD.
A (delta, epsilon) pair counts as feasible when epsilon + (N-1) delta <= 1 - 1e-6 (the SPEC's
"> 1" rule with the w <= 1 - 1e-6 margin; no pair of the SPEC's grid lies in between).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.optimize import minimize

from mewa_bench.design.references import DECIMALS

DELTAS: tuple[float, ...] = (0.075, 0.13125, 0.1875, 0.24375, 0.3)
EPSILONS: tuple[float, ...] = (0.075, 0.1125, 0.15, 0.1875, 0.225)
MARGIN = 1e-6
W_MAX = 1.0 - MARGIN
SIGNIFICANT = 12
N_RANDOM_STARTS = 12
START_SEED = 20230601
SLSQP_OPTIONS = {"maxiter": 500, "ftol": 1e-14}
TINY = 1e-300
ACTIVE_TOL = 1e-7
FEASIBILITY_TOL = 1e-9
REL_TIE = 1e-12

MadScorer = Callable[[np.ndarray, np.ndarray], float]


@dataclass(frozen=True)
class Eq1Structure:
    """Index tables of Eq. 1 for one N: the defined (x, y) pairs and the f2 triples."""

    N: int
    xs: np.ndarray  # x of each defined (x, y), x-major then y-minor
    ys: np.ndarray  # y of each defined (x, y)
    onehot_x: np.ndarray  # (n_xy, N): onehot_x[t, x] = 1 iff xs[t] == x
    sums: np.ndarray  # (N, n_xy, N): sums[j, t, k] = 1 iff r_k is in the sum of c[j, xs[t], ys[t]]
    f2_j: np.ndarray  # the f2 residuals are c[f2_j, f2_t] - d[f2_x] r[f2_y]
    f2_t: np.ndarray
    f2_x: np.ndarray
    f2_y: np.ndarray


@dataclass(frozen=True)
class Eq1Solution:
    """Best SLSQP result of Eq. 1 for one (delta, epsilon)."""

    delta: float
    epsilon: float
    w: tuple[float, ...]
    r: tuple[float, ...]
    objective: float
    n_starts: int
    n_converged: int


@dataclass(frozen=True)
class CandidateResult:
    """One (delta, epsilon) of the search: its Eq. 1 solution and the MAD it scores."""

    delta: float
    epsilon: float
    w: tuple[float, ...]
    r: tuple[float, ...]  # after the power-of-ten scaling
    objective: float  # f1 + f2 at (w, r) as returned
    mad: float  # mad_of(w, r), 12 significant digits


@dataclass(frozen=True)
class AverageWorkerDesign:
    """Selected average worker and rewards for (N, M), with every candidate examined."""

    N: int
    M: int
    w: tuple[float, ...]
    r: tuple[float, ...]
    objective: float
    delta: float
    epsilon: float
    mad: float
    candidates: tuple[CandidateResult, ...] = field(default_factory=tuple)
    skipped: tuple[tuple[float, float], ...] = field(default_factory=tuple)

    def to_dict(self) -> dict:
        """Plain JSON-ready dict (lists instead of tuples)."""
        out = asdict(self)
        out["w"] = list(self.w)
        out["r"] = list(self.r)
        out["candidates"] = [
            {**asdict(c), "w": list(c.w), "r": list(c.r)} for c in self.candidates
        ]
        out["skipped"] = [list(pair) for pair in self.skipped]
        return out


def defined_xy(N: int) -> list[tuple[int, int]]:
    """Defined (x, y) pairs (y <= x, x <= y + N - 2) in x-major, y-minor order."""
    return [(x, y) for x in range(N) for y in range(x + 1) if x <= y + N - 2]


def sum_range(N: int, j: int, x: int, y: int) -> range:
    """Indices k of the r_k subtracted in c[j,x,y]."""
    return range(x - y + j + 1, min(x + j + 1, N))


def eq1_structure(N: int) -> Eq1Structure:
    """Build the index tables of Eq. 1 for N sub-goals."""
    if N < 2:
        raise ValueError(f"Eq. 1 needs N >= 2, got {N}")
    pairs = defined_xy(N)
    position = {pair: t for t, pair in enumerate(pairs)}
    xs = np.array([x for x, _ in pairs], dtype=np.intp)
    ys = np.array([y for _, y in pairs], dtype=np.intp)
    onehot_x = (xs[:, None] == np.arange(N)[None, :]).astype(float)
    sums = np.zeros((N, len(pairs), N))
    for j in range(N):
        for t, (x, y) in enumerate(pairs):
            sums[j, t, list(sum_range(N, j, x, y))] = 1.0
    f2 = [
        (j, position[(x, x)], x, y)
        for j in range(1, N)
        for y in range(j)
        for x in range(j - y, N)
    ]
    f2_j, f2_t, f2_x, f2_y = (np.array(col, dtype=np.intp) for col in zip(*f2))
    return Eq1Structure(N, xs, ys, onehot_x, sums, f2_j, f2_t, f2_x, f2_y)


def worker_d(w: np.ndarray, M: int) -> np.ndarray:
    """d_x = (1 + (M-1) w_x) / (1 - w_x)."""
    return (1.0 + (M - 1) * w) / (1.0 - w)


def c_matrix(s: Eq1Structure, d: np.ndarray, r: np.ndarray) -> np.ndarray:
    """c[j, t] for the t-th defined (x, y): (d_x + y) r_j - (sum of r_k)."""
    return (d[s.xs] + s.ys)[None, :] * r[:, None] - s.sums @ r


def residuals(s: Eq1Structure, d: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(c, e1, e2): f1 = sum(e1**2) over consecutive differences, f2 = sum(e2**2)."""
    c = c_matrix(s, d, r)
    e1 = np.diff(c, axis=1)
    e2 = c[s.f2_j, s.f2_t] - d[s.f2_x] * r[s.f2_y]
    return c, e1, e2


def eq1_terms(w: np.ndarray, r: np.ndarray, M: int) -> tuple[float, float]:
    """(f1, f2) of Eq. 1 at worker w and rewards r (full vectors, r_0 included)."""
    w, r = np.asarray(w, dtype=float), np.asarray(r, dtype=float)
    if w.shape != r.shape or w.ndim != 1:
        raise ValueError(f"w and r must be vectors of the same length N, got {w.shape} and {r.shape}")
    _, e1, e2 = residuals(eq1_structure(len(w)), worker_d(w, M), r)
    return float(np.sum(e1 * e1)), float(np.sum(e2 * e2))


def eq1_objective(w: np.ndarray, r: np.ndarray, M: int) -> float:
    """f1 + f2 of Eq. 1."""
    f1, f2 = eq1_terms(w, r, M)
    return f1 + f2


def objective_and_gradient(
    z: np.ndarray, s: Eq1Structure, M: int
) -> tuple[float, np.ndarray]:
    """f1 + f2 and its gradient in z = (w_0..w_{N-1}, r_1..r_{N-1}), r_0 = -1."""
    N = s.N
    w = z[:N]
    r = np.concatenate(([-1.0], z[N:]))
    d = worker_d(w, M)
    c, e1, e2 = residuals(s, d, r)
    value = float(np.sum(e1 * e1) + np.sum(e2 * e2))

    # Gradient with respect to c, then chained to d and r.
    g_c = np.zeros_like(c)
    g_c[:, 1:] += 2.0 * e1
    g_c[:, :-1] -= 2.0 * e1
    g_r = np.zeros(N)
    g_d = np.zeros(N)
    for i in range(len(e2)):  # a handful of terms; a plain loop keeps summation order fixed
        g_c[s.f2_j[i], s.f2_t[i]] += 2.0 * e2[i]
        g_d[s.f2_x[i]] -= 2.0 * e2[i] * r[s.f2_y[i]]
        g_r[s.f2_y[i]] -= 2.0 * e2[i] * d[s.f2_x[i]]
    g_r += g_c @ (d[s.xs] + s.ys) - np.einsum("jt,jtk->k", g_c, s.sums)
    g_d += (g_c * r[:, None]).sum(axis=0) @ s.onehot_x
    g_w = g_d * M / (1.0 - w) ** 2
    return value, np.concatenate((g_w, g_r[1:]))


def log_objective_and_gradient(
    z: np.ndarray, s: Eq1Structure, M: int
) -> tuple[float, np.ndarray]:
    """log(f1 + f2) and its gradient: same minimisers, but scale-free for SLSQP's ftol."""
    value, grad = objective_and_gradient(z, s, M)
    value = max(value, TINY)
    return math.log(value), grad / value


def is_feasible_pair(N: int, delta: float, epsilon: float) -> bool:
    """Whether some w satisfies w_{N-1} >= epsilon, w_x - w_{x+1} >= delta, w_0 <= 1 - margin."""
    return epsilon + (N - 1) * delta <= W_MAX


def linear_constraints(N: int, delta: float) -> list[dict]:
    """SLSQP inequality constraints (>= 0) on z: w gaps >= delta, r gaps >= margin."""
    rows, rhs = [], []
    for x in range(N - 1):
        row = np.zeros(2 * N - 1)
        row[x], row[x + 1] = 1.0, -1.0
        rows.append(row)
        rhs.append(delta)
    for i in range(1, N - 1):  # r_{i+1} - r_i, both free (r_1 - r_0 is a bound)
        row = np.zeros(2 * N - 1)
        row[N + i], row[N + i - 1] = 1.0, -1.0
        rows.append(row)
        rhs.append(MARGIN)
    if not rows:
        return []
    A, b = np.array(rows), np.array(rhs)
    return [{"type": "ineq", "fun": lambda z: A @ z - b, "jac": lambda z: A}]


def variable_bounds(N: int, epsilon: float) -> list[tuple[float, float]]:
    """Bounds on z: w_x in [0, 1 - margin], w_{N-1} >= epsilon, r in [-1 + margin, -margin]."""
    w_bounds = [(0.0, W_MAX)] * (N - 1) + [(epsilon, W_MAX)]
    r_bounds = [(-1.0 + MARGIN, -MARGIN)] * (N - 1)
    return w_bounds + r_bounds


def repair(w: np.ndarray, r: np.ndarray, delta: float, epsilon: float) -> tuple[np.ndarray, np.ndarray]:
    """Re-impose the constraints exactly, undoing SLSQP's tiny violations (r_0 set to -1)."""
    w = np.clip(np.asarray(w, dtype=float), 0.0, W_MAX)
    N = len(w)
    w[N - 1] = max(w[N - 1], epsilon)
    for x in range(N - 2, -1, -1):
        w[x] = max(w[x], w[x + 1] + delta)
    r = np.asarray(r, dtype=float).copy()
    r[0] = -1.0
    for i in range(1, N):
        r[i] = max(r[i], r[i - 1] + MARGIN)
    r[N - 1] = min(r[N - 1], -MARGIN)
    return w, r


def starting_points(N: int, delta: float, epsilon: float) -> list[np.ndarray]:
    """Fixed starting points: the centre of the feasible set, then fixed-seed random ones."""
    slack = W_MAX - epsilon - (N - 1) * delta
    rng = np.random.default_rng([START_SEED, N, round(delta * 1e6), round(epsilon * 1e6)])
    shares = [np.full(N + 1, 1.0 / (N + 1))] + list(rng.dirichlet(np.ones(N + 1), N_RANDOM_STARTS))
    steps = [np.full(N, 1.0 / N)] + list(rng.dirichlet(np.ones(N), N_RANDOM_STARTS))
    starts = []
    for a, b in zip(shares, steps):
        # w_{N-1} = eps + a_{N-1} slack, w_x = w_{x+1} + delta + a_x slack; a_N is unused slack.
        w = np.empty(N)
        w[N - 1] = epsilon + a[N - 1] * slack
        for x in range(N - 2, -1, -1):
            w[x] = w[x + 1] + delta + a[x] * slack
        r = -1.0 + np.cumsum(b)[: N - 1] * (1.0 - 2 * MARGIN) + MARGIN * np.arange(1, N)
        w, r_full = repair(w, np.concatenate(([-1.0], r)), delta, epsilon)
        starts.append(np.concatenate((w, r_full[1:])))
    return starts


def max_violation(w: np.ndarray, r: np.ndarray, delta: float, epsilon: float) -> float:
    """Largest violation of the constraints of Eq. 1 (0 if feasible)."""
    w, r = np.asarray(w, dtype=float), np.asarray(r, dtype=float)
    gaps = [
        -w.min(),
        w.max() - W_MAX,
        epsilon - w[-1],
        *(delta - (w[:-1] - w[1:])),
        *(MARGIN - np.diff(r)),
        r[-1] + MARGIN,
        abs(r[0] + 1.0),
    ]
    return max(0.0, float(max(gaps)))


def snap_worker(w: np.ndarray, delta: float, epsilon: float) -> np.ndarray:
    """Put w exactly on every constraint SLSQP left it within ACTIVE_TOL of (corners are common)."""
    w = np.clip(np.asarray(w, dtype=float), 0.0, W_MAX)
    N = len(w)
    out = w.copy()
    if w[N - 1] - epsilon < ACTIVE_TOL:
        out[N - 1] = epsilon
    for x in range(N - 2, -1, -1):
        if w[x] - w[x + 1] - delta < ACTIVE_TOL:
            out[x] = out[x + 1] + delta
        else:
            out[x] = max(w[x], out[x + 1] + delta)
    return np.minimum(out, W_MAX)


def residual_matrix(s: Eq1Structure, d: np.ndarray) -> np.ndarray:
    """A with (e1, e2) = A r: every residual of Eq. 1 is linear in r for a fixed worker."""
    columns = []
    for unit in np.eye(s.N):
        _, e1, e2 = residuals(s, d, unit)
        columns.append(np.concatenate((e1.ravel(), e2)))
    return np.column_stack(columns)


def active_reward_rows(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Equalities (C, b), C r = b: r_0 = -1 and every r constraint active (within ACTIVE_TOL) at r."""
    N = len(r)
    rows, rhs = [np.eye(N)[0]], [-1.0]
    for i in range(N - 1):
        if r[i + 1] - r[i] - MARGIN < ACTIVE_TOL:
            rows.append(np.eye(N)[i + 1] - np.eye(N)[i])
            rhs.append(MARGIN)
    if -MARGIN - r[N - 1] < ACTIVE_TOL:
        rows.append(np.eye(N)[N - 1])
        rhs.append(-MARGIN)
    return np.array(rows), np.array(rhs)


def exact_rewards(s: Eq1Structure, w: np.ndarray, M: int, r_guess: np.ndarray) -> np.ndarray | None:
    """Exact minimiser over r of f1 + f2 for a fixed w, with r_guess's active constraints as equalities."""
    A = residual_matrix(s, worker_d(w, M))
    C, b = active_reward_rows(r_guess)
    n, m = A.shape[1], len(b)
    # KKT system of min |A r|^2 subject to C r = b.
    kkt = np.block([[2.0 * A.T @ A, C.T], [C, np.zeros((m, m))]])
    try:
        solution = np.linalg.solve(kkt, np.concatenate((np.zeros(n), b)))
    except np.linalg.LinAlgError:
        return None
    return solution[:n]


def polish(
    s: Eq1Structure, M: int, z: np.ndarray, delta: float, epsilon: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Feasible (w, r) from an SLSQP point z: snapped and exactly re-solved first, then z repaired."""
    N = s.N
    w_raw, r_raw = z[:N], np.concatenate(([-1.0], z[N:]))
    out = []
    w = snap_worker(w_raw, delta, epsilon)
    r = exact_rewards(s, w, M, r_raw)
    if r is not None and max_violation(w, r, delta, epsilon) <= FEASIBILITY_TOL:
        out.append(repair(w, r, delta, epsilon))
    out.append(repair(w_raw, r_raw, delta, epsilon))
    return out


def round_sig(value: float, digits: int = SIGNIFICANT) -> float:
    """Round to `digits` significant digits (stable JSON floats)."""
    return float(f"{value:.{digits}g}")


def solve_eq1(N: int, M: int, delta: float, epsilon: float) -> Eq1Solution:
    """Minimise f1 + f2 with r_0 = -1 by SLSQP from every fixed starting point; keep the best."""
    if M < 2:
        raise ValueError(f"Eq. 1 needs M >= 2, got {M}")
    if not is_feasible_pair(N, delta, epsilon):
        raise ValueError(f"infeasible (delta, epsilon) = ({delta}, {epsilon}) for N = {N}")
    s = eq1_structure(N)
    bounds = variable_bounds(N, epsilon)
    constraints = linear_constraints(N, delta)
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    starts = starting_points(N, delta, epsilon)
    n_converged = 0
    for z0 in starts:
        res = minimize(
            log_objective_and_gradient, z0, args=(s, M), jac=True, method="SLSQP",
            bounds=bounds, constraints=constraints, options=SLSQP_OPTIONS,
        )
        n_converged += bool(res.success)
        for w, r in polish(s, M, res.x, delta, epsilon):
            w, r = np.round(w, DECIMALS), np.round(r, DECIMALS)
            value = eq1_objective(w, r, M)
            # Strict "<" keeps the earliest candidate on ties: the order of starts decides, never chance.
            if np.isfinite(value) and (best is None or value < best[0]):
                best = (value, w, r)
    assert best is not None
    value, w, r = best
    # Near the minimum f1 + f2 is flat to machine precision, so the comparisons above may pick a
    # raw point over a polished one by an ulp; re-polish the winner so r does not depend on that.
    w_p, r_p = (np.round(v, DECIMALS) for v in polish(s, M, np.concatenate((w, r[1:])), delta, epsilon)[0])
    value_p = eq1_objective(w_p, r_p, M)
    if value_p <= value * (1.0 + REL_TIE):
        value, w, r = value_p, w_p, r_p
    return Eq1Solution(
        delta=delta, epsilon=epsilon, w=tuple(float(v) for v in w),
        r=tuple(float(v) for v in r), objective=round_sig(value),
        n_starts=len(starts), n_converged=n_converged,
    )


def mad_key(mad: float) -> float:
    """Comparison key of a MAD: rounded to 12 decimals (as in curation); NaN never wins."""
    return math.inf if math.isnan(mad) else round(mad, DECIMALS)


def select_candidate(candidates: list[CandidateResult]) -> CandidateResult:
    """Smallest MAD; ties go to the earliest candidate in (delta, epsilon) grid order."""
    if not candidates:
        raise ValueError("no candidate to select from")
    return min(candidates, key=lambda c: mad_key(c.mad))  # min keeps the first of equal keys


def design_average_worker(
    N: int,
    M: int,
    mad_of: MadScorer,
    deltas: tuple[float, ...] = DELTAS,
    epsilons: tuple[float, ...] = EPSILONS,
) -> AverageWorkerDesign:
    """Solve Eq. 1 on the (delta, epsilon) grid and keep the solution with the smallest MAD."""
    candidates, skipped = [], []
    for delta in deltas:
        for epsilon in epsilons:
            if not is_feasible_pair(N, delta, epsilon):
                skipped.append((delta, epsilon))
                continue
            sol = solve_eq1(N, M, delta, epsilon)
            r = sol.r  # r_0 = -1 by construction: SPEC section 4's rule -1 <= r_0 < -0.1 holds without rescaling
            w_arr, r_arr = np.array(sol.w), np.array(r)
            objective = round_sig(eq1_objective(w_arr, r_arr, M))
            mad = round_sig(float(mad_of(w_arr, r_arr)))
            candidates.append(CandidateResult(delta, epsilon, sol.w, r, objective, mad))
    best = select_candidate(candidates)
    return AverageWorkerDesign(
        N=N, M=M, w=best.w, r=best.r, objective=best.objective, delta=best.delta,
        epsilon=best.epsilon, mad=best.mad, candidates=tuple(candidates), skipped=tuple(skipped),
    )
