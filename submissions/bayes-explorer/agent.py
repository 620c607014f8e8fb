"""bayes-explorer: a reference MEWA agent that adapts by exploring (issue 11).

It is told neither the task nor the worker (SPEC section 6). What it knows is public: the tasks
listed in the shipped suite files (`ALL_SUITES`) with their worker distributions, and the
t-optimal policy family.

- Task: `mewa_bench.agents.task_inference.TaskBelief` over the public tasks (one per set of
  rules); it acts for the first candidate left.
- Prior over the worker: the meta-train distributions that the suite files list for the task's
  rules, each listing weighted equally (v1 and v2 list the same rules for most tasks, and nothing an
  agent sees tells the suites apart), approximated on the 0.05 grid of each listed family's
  monotone workers: box samplers by the exact cell masses of their clipped band mixtures, cover
  samplers by equal weight per grid point, plus a `floor` share spread evenly over the grid (the
  meta-test workers lie outside the meta-train boxes by construction).
- Posterior: exact on the grid; each second block with x + 1 structures open is a Bernoulli(w_x)
  trial whose outcome the next observation shows.
- Objective: the protocol's score, expected return / the best t-optimal return for the worker.
- Choice at every episode start (episodes counted with `end_episode`): a one-step knowledge
  gradient over the pair's remaining episodes. For each rho1 (which trial types an episode shows)
  the myopic best policy is a candidate; its value is its posterior expected score now plus
  (remaining - 1) times the expected best posterior score after one more episode of it. That
  episode is simulated on posterior draws (the policies' exact chains from
  `mewa_bench.design.replay`); the updated posterior lives on the 0.1 sub-grid. When even perfect
  information would be worth less than `kg_threshold` over the remaining episodes, it plays the
  myopic best (the highest posterior expected score).
- Within an episode, after every trial (`replan=myopic`, the default), it switches to the myopic
  best policy if that beats the current one by `switch_margin`, keeping the run counters.
- Step-level plans (from the second episode on, `step_plan=1`): a *planning worker* takes, per
  mistake type, a posterior quantile of w_x (`plan_quantiles`: 0.5 and 0.9; at 0.9 types it has
  seen little of count as error-prone). For each, the known-worker optimal plan
  (`mewa_bench.design.optimum.optimal_actions`, an action by state and steps left) is a candidate
  if it beats the best t-optimal policy for its planning worker by `plan_margin` in score. A plan
  is fragile (made for w_2 = 0.95 it can score 0 when w_2 = 1), so each candidate is judged by its
  exact score (`optimum.plan_returns`) on the most likely grid workers (`plan_mass` of the
  posterior, at most `plan_support` of them): the episode follows the best candidate if its
  posterior expected score is above the best t-optimal policy's (`plan_check=1`). The planning
  worker is recomputed after every trial, so the plan adapts within the episode. Plans and their
  scores are cached per process by the rounded worker (`plan_quantum`, at most 256 MB).

Exact returns of every policy at every grid worker come from `mewa_bench.design.exact` once per
task and are shared by all agents of a process. Randomness: only `np.random.default_rng([seed,
unit seed])`, so runs are deterministic given the `seed` agent arg and `reset_task(seed=...)`.

Run it: `mewa-bench evaluate submissions/bayes-explorer/agent.py --suite narrow-v2`.
"""

from __future__ import annotations

import sys
import types
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

PRIVILEGED = False
NUM_ACTIONS = 4
EPISODES_PER_PAIR = 10
TINY = 1e-300  # stands in for 0 under log, so that 0 observations x log(0) = 0, not nan
MIN_BEST = 0.1  # smallest best return a score is divided by (curation keeps pairs with >= 0.1)
PLAN_CACHE_BYTES = 256 * 2**20  # step-level plans kept per process (a plan is [T + 1, S] int8, <= 0.7 MB)
COARSE = 0.1  # grid step of the lookahead's support (a sub-grid of the 0.05 grid)
TERMINAL = -1  # the replay chain's terminal node (mewa_bench.design.exact.TERMINAL)


@dataclass(frozen=True)
class Listing:
    """One public worker distribution of a task's rules: its families and meta-train mixture."""

    families: tuple[Any, ...]  # mewa_bench.game.distributions.WorkerFamily
    family_weights: tuple[float, ...]
    cover_weight: float


def task_listings(task: Any) -> Listing:
    """The meta-train distribution a suite lists with `task` (v1: the paper family's box sampler)."""
    from mewa_bench.game.distributions import meta_train_spec, worker_families

    spec = meta_train_spec(task)
    families = worker_families(task)
    if spec is None:
        return Listing(families, (1.0,), 0.0)
    return Listing(families, tuple(float(v) for v in spec["family_weights"]), float(spec["cover_weight"]))


def public_listings(suites: str) -> tuple[list[Any], dict[tuple, list[Listing]]]:
    """One task per set of rules (in suite order), and every distinct listing of each set of rules."""
    from mewa_bench.design.suites import load_suite

    tasks: dict[tuple, Any] = {}
    listings: dict[tuple, list[Listing]] = {}
    for name in suites.split(","):
        for task in load_suite(name.strip()).tasks:
            tasks.setdefault(task.key(), task)
            listing = task_listings(task)
            if listing not in listings.setdefault(task.key(), []):
                listings[task.key()].append(listing)
    return list(tasks.values()), listings


def band_cdf(x: np.ndarray, centre: float, sigma: float) -> np.ndarray:
    """CDF of the paper's box bands for one component: (c - 2s, c - s/2) or (c + s/2, c + 2s), equally likely."""
    out = np.zeros_like(x)
    for lo, hi in ((-2.0, -0.5), (0.5, 2.0)):
        a, b = centre + sigma * lo, centre + sigma * hi
        out += 0.5 * np.clip((x - a) / (b - a), 0.0, 1.0)
    return out


def box_weights(grid: np.ndarray, centre: Sequence[float], sigma: Sequence[float], step: float) -> np.ndarray:
    """Mass of each grid cell under the box sampler (clipping to [0, 1] puts the tails on 0 and 1)."""
    low = np.where(grid <= step / 2, -np.inf, grid - step / 2)
    high = np.where(grid >= 1.0 - step / 2, np.inf, grid + step / 2)
    mass = np.ones(len(grid))
    for x in range(grid.shape[1]):
        mass *= band_cdf(high[:, x], centre[x], sigma[x]) - band_cdf(low[:, x], centre[x], sigma[x])
    return mass


def normalised(weights: np.ndarray) -> np.ndarray:
    """Weights scaled to sum to 1 (all zeros stay zeros)."""
    total = weights.sum()
    return weights / total if total > 0 else weights


def listing_weights(listing: Listing, grid: np.ndarray, step: float) -> np.ndarray:
    """Approximate meta-train probability of each grid worker under one listing."""
    from mewa_bench.game.distributions import is_monotone

    out = np.zeros(len(grid))
    for family, share in zip(listing.families, listing.family_weights):
        member = is_monotone(grid, family.monotone).astype(np.float64)
        box = normalised(box_weights(grid, family.centre, family.sigma, step) * member)
        cover = normalised(member)
        out += share * ((1.0 - listing.cover_weight) * box + listing.cover_weight * cover)
    return normalised(out)


def family_grid(listings: Sequence[Listing], n: int, step: float) -> np.ndarray:
    """Grid workers of every listed family's monotone order, each once, lexicographic."""
    from mewa_bench.game.distributions import worker_grid

    orders = sorted({f.monotone for listing in listings for f in listing.families})
    return np.unique(np.concatenate([worker_grid(n, step, order) for order in orders]), axis=0)


def prior_weights(listings: Sequence[Listing], grid: np.ndarray, step: float, floor: float) -> np.ndarray:
    """The prior on the grid: the listings' mixture (equal shares) with a `floor` share spread evenly."""
    mix = sum(listing_weights(listing, grid, step) for listing in listings) / len(listings)
    return (1.0 - floor) * mix + floor / len(grid)


class TaskModel:
    """For one task's rules: grid, prior, exact policy values per grid worker and the policies' chains."""

    def __init__(self, task: Any, listings: Sequence[Listing], step: float, floor: float, ratio: bool) -> None:
        from mewa_bench.design.exact import expected_returns
        from mewa_bench.design.policies import toptimal_family
        from mewa_bench.design.replay import replay_chain

        self.task = task
        self.policies = toptimal_family(task.N)
        self.grid = family_grid(listings, task.N, step)
        self.log_prior = np.log(np.maximum(prior_weights(listings, self.grid, step, floor), TINY))
        self.log_w = np.log(np.maximum(self.grid, TINY))
        self.log_not_w = np.log(np.maximum(1.0 - self.grid, TINY))
        returns = expected_returns(task, self.policies, self.grid)  # [P, G]
        # the protocol's score: return / the best t-optimal return for the worker (curated workers: >= 0.1)
        self.denominator = np.maximum(returns.max(axis=0), MIN_BEST) if ratio else np.ones(len(self.grid))
        self.values = returns / self.denominator
        self.best_values = self.values.max(axis=0)  # [G]: what knowing the worker would give
        self.chain = replay_chain(task, self.policies)
        coarse = np.round(np.round(self.grid / COARSE) * COARSE, 12)  # rounding keeps the monotone order
        self.coarse_grid, self.coarse_of = np.unique(coarse, axis=0, return_inverse=True)
        self.coarse_of = self.coarse_of.ravel()
        self.coarse_log_w = np.log(np.maximum(self.coarse_grid, TINY))
        self.coarse_log_not_w = np.log(np.maximum(1.0 - self.coarse_grid, TINY))
        here = np.array([int(np.flatnonzero((self.grid == c).all(axis=1))[0]) for c in self.coarse_grid])
        self.coarse_values = self.values[:, here]  # [P, C]: values at the coarse points themselves
        columns = [np.unique(self.grid[:, x], return_inverse=True) for x in range(self.grid.shape[1])]
        self.levels = [levels for levels, _ in columns]  # the values w_x takes on the grid
        self.level_of = [inverse.ravel() for _, inverse in columns]  # [G]: each grid worker's level of w_x

    def log_posterior(self, mistakes: np.ndarray, successes: np.ndarray) -> np.ndarray:
        """Unnormalised log posterior of each grid worker given mistake counts per type."""
        n = self.grid.shape[1]
        return self.log_prior + self.log_w @ mistakes[:n] + self.log_not_w @ successes[:n]

    def simulate(self, workers: np.ndarray, uniforms: np.ndarray, chosen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mistakes and successes per type [C, S, N] of one episode of each chosen policy on each worker.

        `uniforms[t, s]` decides the trial at step t for worker s, the same for every policy.
        """
        chain, n_pol, n_work = self.chain, len(chosen), len(workers)
        n = workers.shape[1]
        w = np.concatenate([workers, np.zeros((n_work, 1))], axis=1)  # column -1: no trial
        node = np.repeat(chain.roots[chosen], n_work)
        lane = np.tile(np.arange(n_work), n_pol)
        counts = np.zeros((2, n_pol * n_work, n + 1))
        live = np.flatnonzero(node != TERMINAL)
        for t in range(len(uniforms)):
            if live.size == 0:
                break
            branch = chain.first[node[live]]
            x = chain.x[branch]
            mistake = uniforms[t, lane[live]] < w[lane[live], x]
            np.add.at(counts, (mistake.astype(np.int64), live, x), 1.0)
            nxt = np.where(mistake, chain.bad[branch], chain.ok[branch])
            node[live] = nxt
            live = live[nxt != TERMINAL]
        shaped = counts[:, :, :n].reshape(2, n_pol, n_work, n)
        return shaped[1], shaped[0]


@dataclass
class Settings:
    """The agent's knobs (agent args)."""

    grid_step: float = 0.05
    floor: float = 0.3
    scenarios: int = 48
    horizon: int = 60
    kg_threshold: float = 0.002
    kg_margin: float = 0.0
    ratio: int = 1
    replan: str = "myopic"  # or "none": keep the episode's policy to its end
    switch_margin: float = 0.0
    episodes: int = EPISODES_PER_PAIR
    step_plan: int = 1  # 0: t-optimal policies only
    plan_from: int = 1  # first episode (0-based) that may be played by the step-level plan
    plan_quantiles: str = "0.5,0.9"  # candidate planning workers: these posterior quantiles of each w_x
    plan_margin: float = 0.005  # a plan must beat the best t-optimal policy for its planning worker by this much (score)
    plan_quantum: float = 0.025  # planning workers are rounded to this grid (plans are cached by it)
    plan_check: int = 1  # 1: play the plan only if its posterior expected score beats the myopic best's
    plan_mass: float = 0.99  # posterior mass of the grid workers the check evaluates the plan on
    plan_support: int = 64  # at most this many of them (the most likely)


def posterior_of(log_post: np.ndarray) -> np.ndarray:
    """Normalised posterior from an unnormalised log posterior."""
    weight = np.exp(log_post - log_post.max())
    return weight / weight.sum()


def candidates(model: TaskModel, now: np.ndarray) -> np.ndarray:
    """Policies worth exploring with: for each rho1 (which trial types an episode shows) the myopic best."""
    rho1 = np.array([p.rho1 for p in model.policies])
    return np.array([int(np.flatnonzero(rho1 == r)[np.argmax(now[rho1 == r])]) for r in np.unique(rho1)])


def knowledge_gradient(model: TaskModel, post: np.ndarray, chosen: np.ndarray, remaining: int, settings: Settings,
                       rng: np.random.Generator) -> np.ndarray:
    """Per chosen policy: the expected best posterior value after one more episode of it, x (remaining - 1).

    The next episode is simulated on `scenarios` posterior draws; the updated posterior lives on the
    0.1 sub-grid, each point carrying the posterior mass of the 0.05 points that round to it.
    """
    coarse = np.bincount(model.coarse_of, weights=post, minlength=len(model.coarse_grid))
    keep = np.flatnonzero(coarse > 1e-12 * coarse.max())
    log_prior = np.log(coarse[keep])
    truth = model.grid[rng.choice(len(post), size=settings.scenarios, p=post)]
    uniforms = rng.random((settings.horizon, settings.scenarios))
    mistakes, successes = model.simulate(truth, uniforms, chosen)  # [C, S, N]
    log_like = (log_prior + mistakes @ model.coarse_log_w[keep].T
                + successes @ model.coarse_log_not_w[keep].T)  # [C, S, L]
    weight = np.exp(log_like - log_like.max(axis=2, keepdims=True))
    weight /= weight.sum(axis=2, keepdims=True)
    after = weight @ model.coarse_values[:, keep].T  # [C, S, Q]: each policy's value after the episode
    return (remaining - 1) * after.max(axis=2).mean(axis=1)


def choose(model: TaskModel, log_post: np.ndarray, remaining: int, settings: Settings,
           rng: np.random.Generator, current: int | None = None) -> int:
    """Index of the policy to play: at an episode start (`current` None) by knowledge gradient while
    information is worth it, else myopic; mid-episode the myopic best if it beats `current` by `switch_margin`."""
    post = posterior_of(log_post)
    now = model.values @ post
    if current is not None:
        best = int(np.argmax(now))
        return best if now[best] > now[current] + settings.switch_margin else current
    perfect_information = float(post @ model.best_values - now.max())
    if remaining <= 1 or (remaining - 1) * perfect_information < settings.kg_threshold:
        return int(np.argmax(now))
    chosen = candidates(model, now)
    total = now[chosen] + knowledge_gradient(model, post, chosen, remaining, settings, rng)
    myopic = int(np.argmax(now))
    best = int(np.argmax(total))
    return int(chosen[best]) if total[best] > total[chosen == myopic].max() + settings.kg_margin else myopic


class BayesExplorerAgent:
    """Infers the task and the worker; plays the t-optimal policy with the best knowledge-gradient value."""

    def __init__(self, suite: str | None = None, seed: int | str = 0, **knobs: Any) -> None:
        from mewa_bench.design.suites import ALL_SUITES
        from mewa_bench.agents.task_inference import TaskBelief

        self.suites = suite or ",".join(ALL_SUITES)
        tasks, self.listings = _shared_public(self.suites)
        self.task_belief = TaskBelief(tasks)
        self.seed = int(seed)
        self.settings = Settings(**{k: type(getattr(Settings, k))(v) for k, v in knobs.items()})
        if self.settings.replan not in ("myopic", "none"):
            raise ValueError(f"replan must be myopic or none, got {self.settings.replan!r}")
        self.reset_task()

    def reset_task(self, seed: int | None = None) -> None:
        """A new hidden pair: forget the task candidates and the evidence; reseed."""
        self.rng = np.random.default_rng([self.seed] if seed is None else [self.seed, seed])
        self.task_belief.reset()
        self.mistakes = np.zeros(NUM_ACTIONS)
        self.successes = np.zeros(NUM_ACTIONS)
        self.episodes_done = 0
        self.policy: Any = None
        self.memory: Any = None
        self.log_post: np.ndarray | None = None
        self.posterior_task: Any = None
        self.episode_starting = True
        self.planned_episode = False
        self.episode_quantile = 0.0  # the planning worker's quantile of a planned episode
        self.steps_done = 0
        self.planning: dict[tuple[int, float], np.ndarray] = {}  # planning workers until the next trial

    def act(self, obs: Any) -> int:
        """The chosen policy's action for the candidate task's state."""
        from mewa_bench.game.rules import state_from_observation
        from mewa_bench.protocol.agent import state_vector

        obs = state_vector(obs)
        if self.episode_starting:
            self.task_belief.start_episode(obs)
            self.episode_starting = False
            self.steps_done = 0
            self.planned_episode = self.step_plan_pays()
            if not self.planned_episode:
                self.choose_policy(reset_memory=True)
        task = self.task_belief.task
        if self.planned_episode and task is not None:
            self.steps_done += 1
            return self.planned_action(task, state_from_observation(task, obs))
        if task is None or self.policy is None:  # no public task explains what was seen
            return int(self.rng.integers(NUM_ACTIONS))
        choice = self.policy.choices(task, state_from_observation(task, obs), self.memory)[0]
        self.memory = choice.memory
        return int(choice.action)

    def observe(self, transition: Any) -> None:
        """Narrow the task candidates, record the trial seen (if any) and re-plan (the step-level plan
        re-plans by itself: its planning worker follows the posterior)."""
        acted_for = self.task_belief.task
        why = self.task_belief.update(transition)
        observed = why is not None and why.mistake_type >= 0
        if observed:
            self.planning = {}
            (self.mistakes if why.mistaken else self.successes)[why.mistake_type] += 1
            if self.log_post is not None and self.task_belief.task is self.posterior_task:
                model = self.model(self.posterior_task)
                column = model.log_w if why.mistaken else model.log_not_w
                self.log_post = self.log_post + column[:, why.mistake_type]
        if transition.terminated or transition.truncated:
            self.episode_starting = True
        elif self.planned_episode:
            pass
        elif self.task_belief.task is not acted_for:
            self.choose_policy(reset_memory=True)
        elif observed and self.settings.replan != "none":
            self.choose_policy(reset_memory=False)

    def step_plan_pays(self) -> bool:
        """Whether this episode follows a step-level plan, and for which planning worker: the candidate
        (one per `plan_quantiles`) with the highest posterior expected score, if that is above the best
        t-optimal policy's and its gain at its own planning worker is at least `plan_margin`."""
        s = self.settings
        if not s.step_plan or self.episodes_done < s.plan_from or self.task_belief.task is None:
            return False
        task = self.task_belief.task
        quantiles = [q for q in self.quantiles() if self.step_plan(task, q)[1] >= s.plan_margin]
        if not quantiles:
            return False
        if not s.plan_check:
            self.episode_quantile = quantiles[-1]
            return True
        support, weight = self.likely_workers(task)
        scores = [float(self.plan_scores(task, q, support) @ weight) for q in quantiles]
        best = int(np.argmax(scores))
        self.episode_quantile = quantiles[best]
        return scores[best] > float((self.model(task).values[:, support] @ weight).max())

    def quantiles(self) -> list[float]:
        """The candidate planning workers' posterior quantiles, ascending."""
        return sorted(float(q) for q in self.settings.plan_quantiles.split(","))

    def likely_workers(self, task: Any) -> tuple[np.ndarray, np.ndarray]:
        """The most likely grid workers (`plan_mass` of the posterior, at most `plan_support`) and their
        renormalised posterior weights: where a plan is judged.

        A plan is made for one planning worker and can fail outright on workers close to it (a plan for
        w_2 = 0.95 scores 0 when w_2 = 1), so it is weighed on the workers the agent believes in.
        """
        s = self.settings
        post = posterior_of(self.current_log_posterior())
        order = np.argsort(-post, kind="stable")
        count = int(np.searchsorted(np.cumsum(post[order]), s.plan_mass) + 1)
        support = order[: min(count, s.plan_support, len(order))]
        return support, post[support] / post[support].sum()

    def plan_scores(self, task: Any, quantile: float, support: np.ndarray) -> np.ndarray:
        """A step-level plan's score at the grid workers `support` (exact; cached with the plan)."""
        from mewa_bench.design.optimum import plan_returns

        model = self.model(task)
        actions, _, known = self.step_plan(task, quantile, with_scores=True)
        missing = [int(g) for g in support if int(g) not in known]
        if missing:
            scores = plan_returns(task, actions, model.grid[missing]) / model.denominator[missing]
            known.update(zip(missing, scores.tolist()))
        return np.array([known[int(g)] for g in support])

    def step_plan(self, task: Any, quantile: float, with_scores: bool = False) -> tuple:
        """The known-worker optimal actions [T + 1, S] for the planning worker of `quantile` and their
        score gain over the best t-optimal policy for that worker (and, `with_scores`, the plan's scores
        known so far by grid worker); cached per process by the model and the rounded worker."""
        from mewa_bench.design.exact import expected_returns
        from mewa_bench.design.optimum import known_worker_optimum, optimal_actions

        worker = self.planning_worker(task, quantile)
        key = (self.model_key(task), tuple(worker))  # the scores are by the model's grid
        plans = _shared_plans()
        if key in plans:
            plans.move_to_end(key)
        else:
            best_t = float(expected_returns(task, self.model(task).policies, [worker]).max())
            gain = (float(known_worker_optimum(task, [worker])[0]) - best_t) / max(best_t, MIN_BEST)
            plans[key] = (optimal_actions(task, worker), gain, {})
            while sum(actions.nbytes + 64 * len(known) for actions, _, known in plans.values()) > PLAN_CACHE_BYTES:
                plans.popitem(last=False)  # least recently used
        return plans[key] if with_scores else plans[key][:2]

    def planned_action(self, task: Any, state: Any) -> int:
        """The episode's step-level plan's action in `state` with T - steps_done + 1 steps left."""
        from mewa_bench.design.exact import structural_task
        from mewa_bench.game.table import transition_table

        table = transition_table(structural_task(task))  # cached per task by the game layer
        left = max(task.T - self.steps_done + 1, 1)
        return int(self.step_plan(task, self.episode_quantile)[0][left, table.index[state]])

    def planning_worker(self, task: Any, quantile: float) -> np.ndarray:
        """Per component, the posterior `quantile` of w_x (at 0.9, pessimistic: components the agent has
        seen little of count as error-prone), rounded to `plan_quantum`; kept until the next trial."""
        key = (id(task), quantile)
        if key in self.planning:
            return self.planning[key]
        model, s = self.model(task), self.settings
        post = posterior_of(self.current_log_posterior())
        worker = np.array([model.levels[x][np.searchsorted(np.cumsum(np.bincount(model.level_of[x], weights=post)),
                                                           quantile - 1e-12).clip(max=len(model.levels[x]) - 1)]
                           for x in range(task.N)])
        self.planning[key] = np.round(np.round(worker / s.plan_quantum) * s.plan_quantum, 6)
        return self.planning[key]

    def end_episode(self) -> None:
        """Count the episode; the next act() starts another of the same pair."""
        self.episodes_done += 1
        self.episode_starting = True

    def current_log_posterior(self) -> np.ndarray | None:
        """Log posterior over the candidate task's grid (recomputed when the candidate changes)."""
        task = self.task_belief.task
        if task is None:
            return None
        if task is not self.posterior_task or self.log_post is None:
            self.log_post = self.model(task).log_posterior(self.mistakes, self.successes)
            self.posterior_task = task
        return self.log_post

    def choose_policy(self, reset_memory: bool) -> None:
        """Switch to the chosen policy, keeping run counters within its limits mid-episode."""
        log_post = self.current_log_posterior()
        if log_post is None:
            self.policy = None
            return
        model = self.model(self.task_belief.task)
        remaining = max(self.settings.episodes - self.episodes_done, 1)
        current = None if reset_memory or self.policy is None else model.policies.index(self.policy)
        best = model.policies[choose(model, log_post, remaining, self.settings, self.rng, current)]
        if reset_memory or self.policy is None:
            self.memory = best.initial_memory()
        elif best != self.policy:
            run1, run2 = self.memory
            self.memory = (min(run1, best.rho1), min(run2, best.rho2))
        self.policy = best

    def model(self, task: Any) -> TaskModel:
        """The task's model, built once per process (about 1 s for N = 4)."""
        shared = _shared_models()
        s = self.settings
        key = self.model_key(task)
        if key not in shared:
            shared[key] = TaskModel(task, self.listings[task.key()], s.grid_step, s.floor, bool(s.ratio))
        return shared[key]

    def model_key(self, task: Any) -> tuple:
        """What a task model depends on."""
        s = self.settings
        return (self.suites, task.key(), s.grid_step, s.floor, s.ratio)

    def posterior_mean(self) -> np.ndarray | None:
        """The posterior mean worker for the candidate task (None if no candidate is left)."""
        log_post = self.current_log_posterior()
        return None if log_post is None else posterior_of(log_post) @ self.model(self.task_belief.task).grid


def make_agent(observation_space: Any, action_space: Any, **kwargs: Any) -> BayesExplorerAgent:
    """Build the agent; agent args: suite, seed and the fields of `Settings`."""
    if getattr(action_space, "n", NUM_ACTIONS) != NUM_ACTIONS:
        raise ValueError(f"expected the MEWA action space Discrete({NUM_ACTIONS}), got {action_space}")
    kwargs.pop("checkpoint", None)
    return BayesExplorerAgent(**kwargs)


def _cache() -> types.ModuleType:
    """One process-wide holder (this file may be imported once per agent object)."""
    holder = sys.modules.get(_CACHE_MODULE)
    if holder is None:
        holder = sys.modules[_CACHE_MODULE] = types.ModuleType(_CACHE_MODULE)
        holder.models = {}  # type: ignore[attr-defined]
        holder.public = {}  # type: ignore[attr-defined]
        holder.plans = OrderedDict()  # type: ignore[attr-defined]
    return holder


def _shared_models() -> dict:
    """Task models shared by every agent of the process."""
    return _cache().models  # type: ignore[attr-defined]


def _shared_plans() -> OrderedDict:
    """Step-level plans shared by every agent of the process, least recently used first."""
    return _cache().plans  # type: ignore[attr-defined]


def _shared_public(suites: str) -> tuple[list[Any], dict[tuple, list[Listing]]]:
    """Public tasks and listings, loaded once per process."""
    public = _cache().public  # type: ignore[attr-defined]
    if suites not in public:
        public[suites] = public_listings(suites)
    return public[suites]


_CACHE_MODULE = "_mewa_bayes_explorer_models"
