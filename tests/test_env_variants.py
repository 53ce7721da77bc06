"""Delay, bandwidth, moving targets and evidence decay (beyond the paper) against a slow, direct reference.

:class:`SlowReference` is written from the rules in docs/ENVIRONMENT.md ("Delay, bandwidth and moving
targets") with plain Python loops over environments, UAVs, sources, detections and cells. It keeps, for every
UAV i and source q, the *set* of q's detections that i holds (the literal max-plus-sum state), sends
messages as sets, and sums counts from scratch each step. It takes only the scene after a reset and the
random numbers (drawn from a copy of the core's generator in the documented order), never the core's
internal tensors, and is compared with the batched core at every step.
"""

from __future__ import annotations

import copy
import math

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from mcrs.env import MCRSCore, MCRSEnv, scenario
from mcrs.env.belief import belief_masses
from mcrs.env.config import EnvConfig
from mcrs.env.core import MOVES


def _f32(value: float) -> float:
    """The float32 value the core compares random numbers with."""
    return float(torch.tensor(value, dtype=torch.float32))


class SlowReference:
    """One rollout of every environment of ``core`` after its reset, re-derived from the rules."""

    def __init__(self, cfg: EnvConfig, core: MCRSCore, reading: torch.Tensor) -> None:
        self.cfg = cfg
        self.E, self.N, self.K = cfg.num_envs, cfg.n_uavs, cfg.n_targets
        self.keep = 1.0 - cfg.evidence_decay
        self.t = 0
        self.uav = [[tuple(p) for p in core.uav_pos[e].tolist()] for e in range(self.E)]
        self.targets = [[tuple(p) for p in core.target_pos[e].tolist()] for e in range(self.E)]
        self.no_fly = [{tuple(p) for p in core.no_fly_pos[e].tolist()} for e in range(self.E)]
        # detections[e][q]: list of (step, cell, channel); known[e][i][q]: set of indices into it.
        self.detections = [[[] for _ in range(self.N)] for _ in range(self.E)]
        self.known = [[[set() for _ in range(self.N)] for _ in range(self.N)] for _ in range(self.E)]
        self.in_flight: list[list[tuple[int, int, list[set]]]] = [[] for _ in range(self.E)]
        for e in range(self.E):
            for q in range(self.N):
                self._detect(e, q, bool(reading[e, q]))
        self.discovered = [set() for _ in range(self.E)]  # D_find: cells ever >= tau
        self.found_once = [set() for _ in range(self.E)]  # dynamic mode: targets ever found
        self.total_unknown = [0.0] * self.E
        self.metrics: dict[str, list[float]] = {}
        self._global_belief_and_metrics(initial=True)

    # ---------------------------------------------------------------- the rules, literally
    def cell(self, xy: tuple[int, int]) -> int:
        return xy[0] * self.cfg.height + xy[1]

    def _detect(self, e: int, q: int, positive: bool) -> None:
        self.detections[e][q].append((self.t, self.cell(self.uav[e][q]), 0 if positive else 1))
        self.known[e][q][q].add(len(self.detections[e][q]) - 1)

    def step(self, action: torch.Tensor, draws: torch.Generator) -> list[list[float]]:
        cfg, E, N = self.cfg, self.E, self.N
        self.t += 1
        if cfg.target_motion == "random_walk":
            tries = torch.rand(E, self.K, generator=draws)
            move = torch.randint(0, 8, (E, self.K), generator=draws)
            for e in range(E):
                start = list(self.targets[e])
                taken = set(start)
                for k in range(self.K):
                    if not tries[e, k].item() < _f32(cfg.target_move_prob):
                        continue
                    dx, dy = MOVES[move[e, k].item()]
                    x, y = start[k][0] + dx, start[k][1] + dy
                    on_grid = 0 <= x < cfg.width and 0 <= y < cfg.height
                    # Lower-indexed targets were handled first: a cell one of them moved to is taken.
                    if on_grid and (x, y) not in self.no_fly[e] and (x, y) not in taken:
                        taken.add((x, y))
                        self.targets[e][k] = (x, y)
        for e in range(E):
            for i in range(N):
                dx, dy = MOVES[action[e, i].item()]
                self.uav[e][i] = (self.uav[e][i][0] + dx, self.uav[e][i][1] + dy)
        chance = torch.rand(E, N, generator=draws)
        for e in range(E):
            for i in range(N):
                on_target = self.uav[e][i] in self.targets[e]
                p = cfg.p_detect if on_target else cfg.p_false_alarm
                self._detect(e, i, chance[e, i].item() < _f32(p))
        for e in range(E):
            self._communicate(e)
        return self._global_belief_and_metrics()

    def neighbours(self, e: int, i: int) -> list[int]:
        (xi, yi) = self.uav[e][i]
        return [
            j
            for j in range(self.N)
            if j != i and math.hypot(self.uav[e][j][0] - xi, self.uav[e][j][1] - yi) < self.cfg.comm_range
        ]

    def _communicate(self, e: int) -> None:
        cfg, N = self.cfg, self.N
        for arrival, i, message in list(self.in_flight[e]):
            if arrival == self.t:
                for q in range(N):
                    self.known[e][i][q] |= message[q]
        self.in_flight[e] = [m for m in self.in_flight[e] if m[0] != self.t]
        rounds = cfg.rounds_per_step
        budget = math.inf if cfg.comm_budget is None else cfg.comm_budget
        working = copy.deepcopy(self.known[e])
        remaining = {(i, j): budget for i in range(N) for j in range(N)}
        for _ in range(rounds):
            before = copy.deepcopy(working)
            for i in range(N):
                for j in self.neighbours(e, i):
                    pending = {q: sorted(before[j][q] - before[i][q]) for q in range(N)}  # oldest first
                    for q in sorted(range(N), key=lambda q: (-len(pending[q]), q)):
                        n = min(len(pending[q]), remaining[i, j])
                        working[i][q] |= set(pending[q][: int(n)])
                        remaining[i, j] -= n
        for i in range(N):
            if cfg.comm_delay == 0:
                self.known[e][i] = working[i]
            else:
                self.in_flight[e].append((self.t + cfg.comm_delay, i, working[i]))

    def uav_counts(self) -> torch.Tensor:
        """``[E, N, C, 2]`` float64: sum over held detections of (1 - decay)^(t - s)."""
        counts = torch.zeros(self.E, self.N, self.cfg.n_cells, 2, dtype=torch.float64)
        for e in range(self.E):
            for i in range(self.N):
                for q in range(self.N):
                    for index in self.known[e][i][q]:
                        s, cell, channel = self.detections[e][q][index]
                        counts[e, i, cell, channel] += self.keep ** (self.t - s)
        return counts

    def global_counts(self) -> torch.Tensor:
        counts = torch.zeros(self.E, self.cfg.n_cells, 2, dtype=torch.float64)
        for e in range(self.E):
            for q in range(self.N):
                for s, cell, channel in self.detections[e][q]:
                    counts[e, cell, channel] += self.keep ** (self.t - s)
        return counts

    def known_zones(self, e: int) -> set[int]:
        """The cells every belief map holds as known and empty (no_fly_prior=known): the no-fly cells."""
        return {self.cell(z) for z in self.no_fly[e]} if self.cfg.no_fly_prior == "known" else set()

    def _global_belief_and_metrics(self, initial: bool = False) -> list[list[float]]:
        cfg = self.cfg
        counts = self.global_counts()
        _, full, unknown = belief_masses(counts[..., 0].float(), counts[..., 1].float(), cfg.m_f, cfg.m_e)
        terms = []
        for e in range(self.E):
            free = [c for c in range(cfg.n_cells) if c not in self.known_zones(e)]
            total = sum(unknown[e, c].item() for c in free)
            r1 = cfg.w_uncertainty * (self.total_unknown[e] - total)
            self.total_unknown[e] = total
            above = {c for c in free if full[e, c].item() >= cfg.target_threshold}
            target_cells = [self.cell(xy) for xy in self.targets[e]]
            new_cells = above - self.discovered[e]
            self.discovered[e] |= above
            if cfg.dynamic:
                found = {k for k in range(self.K) if target_cells[k] in above}
                new_targets = len(found - self.found_once[e])
                self.found_once[e] |= found
                targets_found, false = len(found), len(above - set(target_cells))
            else:
                new_targets = len(new_cells & set(target_cells))
                targets_found = len(self.discovered[e] & set(target_cells))
                false = len(self.discovered[e] - set(target_cells))
            # r2: eq. 24 pays every cell reaching tau for the first time; "target" only real targets.
            new = len(new_cells) if cfg.discovery_rule == "belief" else new_targets
            new = 0 if initial else new
            no_fly = sum(
                _charged(cfg, math.dist(u, z), cfg.no_fly_safety) for u in self.uav[e] for z in self.no_fly[e]
            )
            close = sum(
                _charged(cfg, math.dist(self.uav[e][i], self.uav[e][j]), cfg.uav_safety)
                for i in range(self.N)
                for j in range(i + 1, self.N)
            )
            sensed = sum(counts[e, c].sum().item() > 0 for c in range(cfg.n_cells))
            terms.append([r1, cfg.w_discovery * new, -cfg.w_no_fly * no_fly, -cfg.w_collision * close])
            for name, value in (
                ("uncertainty", total),
                ("targets_found", targets_found),
                ("false_discoveries", false),
                ("coverage", sensed / cfg.n_cells),
            ):
                self.metrics.setdefault(name, [0.0] * self.E)[e] = float(value)
        return terms


def _charged(cfg: EnvConfig, distance: float, safe: float) -> bool:
    """r3/r4 by the rule's words: enter charges distances < d, near distances <= d."""
    return distance < safe if cfg.safety_rule == "enter" else distance <= safe


def compare_with_reference(cfg: EnvConfig, steps: int, seed: int) -> MCRSCore:
    """Step the core with random allowed actions and check it against :class:`SlowReference`."""
    core = MCRSCore(cfg)
    core.seed(seed)
    result = core.reset()
    reference = SlowReference(cfg, core, result.reading)
    actions = torch.Generator().manual_seed(seed + 1)
    exact = cfg.evidence_decay == 0
    for t in range(1, steps + 1):
        scores = torch.rand(result.action_mask.shape, generator=actions).masked_fill(~result.action_mask, -1)
        action = scores.argmax(-1)
        draws = torch.Generator()
        draws.set_state(core.generator.get_state())  # the same random numbers, drawn by the reference
        result = core.step(action)
        terms = torch.tensor(reference.step(action, draws), dtype=torch.float32)
        where = f"{cfg.name} step {t}"
        assert result.position.tolist() == [list(map(list, u)) for u in reference.uav], where
        assert core.target_pos.tolist() == [list(map(list, k)) for k in reference.targets], where
        cells = core.target_pos[..., 0] * cfg.height + core.target_pos[..., 1]
        assert torch.equal(core.is_target.nonzero()[:, 1].view_as(cells), cells.sort(-1).values), where
        expected = reference.uav_counts()
        got = core.counts_now().view(cfg.num_envs, cfg.n_uavs, cfg.n_cells, 2).to(torch.float64)
        expected_global = reference.global_counts()
        got_global = result.state_counts.to(torch.float64)
        if exact:
            assert torch.equal(got, expected), where
            assert torch.equal(got_global, expected_global), where
        else:
            assert torch.allclose(got, expected, rtol=1e-5, atol=1e-6), where
            assert torch.allclose(got_global, expected_global, rtol=1e-5, atol=1e-6), where
        _, full, unknown = belief_masses(expected[..., 0].float(), expected[..., 1].float(), cfg.m_f, cfg.m_e)
        for e in range(cfg.num_envs):  # known zones read m(U) = m(F) = 0 in every UAV's map
            for c in reference.known_zones(e):
                unknown[e, :, c] = full[e, :, c] = 0.0
        published = result.belief_map.view(cfg.num_envs, cfg.n_uavs, 2, cfg.n_cells)
        assert torch.allclose(published[:, :, 0], unknown, atol=1e-5), where
        assert torch.allclose(published[:, :, 1], full, atol=1e-5), where
        assert torch.allclose(result.reward_terms, terms, atol=1e-4), where
        for name, values in reference.metrics.items():
            assert torch.allclose(result.metrics[name], torch.tensor(values), atol=1e-4), (where, name)
    return core


VARIANTS = {
    "delay": {"comm_delay": 2},
    "delay_rounds": {"comm_delay": 1, "comm_rounds": 2},
    "budget": {"comm_budget": 2},
    "budget_flood": {"comm_budget": 3, "comm_rounds": "flood"},
    "random_walk": {"target_motion": "random_walk", "target_move_prob": 0.4},
    "decay": {"evidence_decay": 0.05},
    "all": {
        "comm_delay": 2,
        "comm_budget": 3,
        "target_motion": "random_walk",
        "target_move_prob": 0.3,
        "evidence_decay": 0.03,
    },
}


def variant_config(name: str, variant: str) -> EnvConfig:
    # comm_range 7 links more UAVs than the paper's 5, so that budgets and relays bind more often.
    return scenario(name, num_envs=2, expose_beliefs=True, comm_range=7.0, **VARIANTS[variant])


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_variant_matches_the_slow_reference(variant):
    compare_with_reference(variant_config("map10", variant), steps=25, seed=5)


@pytest.mark.slow
@pytest.mark.parametrize("variant", sorted(VARIANTS))
@pytest.mark.parametrize("name", ["map15", "map20"])
def test_variant_matches_the_slow_reference_on_larger_maps(name, variant):
    """The same on the larger maps (slow set: the reference is plain Python)."""
    compare_with_reference(variant_config(name, variant), steps=24, seed=5)


#: The older readings by name: the penalty rule, the zones shown as unread beliefs, r2 for targets only.
READINGS = {
    "paper": {},
    "near": {"safety_rule": "near"},
    "unread_zones": {"no_fly_view": "belief", "no_fly_prior": "unknown"},
    "target_r2": {"discovery_rule": "target"},
    "lured": {"no_fly_view": "belief", "no_fly_prior": "unknown", "discovery_rule": "target"},
}


@pytest.mark.parametrize("reading", sorted(READINGS))
def test_the_reference_agrees_with_the_paper_defaults(reading):
    """With every variant off the reference is the paper: it must match the core (and its oracle tests),
    at the defaults and under each older reading by name."""
    compare_with_reference(
        scenario("map10", num_envs=2, expose_beliefs=True, **READINGS[reading]), steps=30, seed=2
    )


@pytest.mark.parametrize("variant", ["decay", "random_walk"])
def test_dynamic_variants_under_the_old_discovery_rule_match_the_reference(variant):
    cfg = variant_config("map10", variant).replace(discovery_rule="target", no_fly_prior="unknown")
    compare_with_reference(cfg, steps=25, seed=5)


def test_a_tight_budget_slows_the_spread_of_knowledge():
    """The budget binds: with 1 detection per link and step, UAVs hold fewer counts than unlimited."""
    held = {}
    for budget in (None, 1):
        cfg = scenario("map10", num_envs=4, comm_range=math.inf, comm_budget=budget)
        core = compare_with_reference(cfg.replace(expose_beliefs=True), steps=12, seed=3)
        held[budget] = core.counts.sum().item()
    assert held[1] < held[None]


def test_delay_holds_messages_back_and_a_reset_drops_them():
    cfg = scenario("map10", num_envs=2, comm_range=math.inf, comm_delay=3)
    core = MCRSCore(cfg)
    core.seed(0)
    result = core.reset()
    for _ in range(3):  # nothing sent at steps 1..3 arrives before step 4
        result = core.step(result.action_mask.float().argmax(-1))
        assert torch.equal(core.known.diagonal(dim1=1, dim2=2), core.known.sum(-1))  # only own detections
    result = core.step(result.action_mask.float().argmax(-1))
    assert (core.known.sum(-1) > core.known.diagonal(dim1=1, dim2=2)).all()  # step 1's messages arrived
    core.reset(torch.tensor([True, False]))
    assert not core.channel.in_flight[0].any() and core.channel.in_flight[1].any()


def test_moving_targets_stay_on_free_cells_and_found_targets_follow_the_current_cell():
    cfg = scenario("map20", num_envs=16, target_motion="random_walk", target_move_prob=1.0)
    core = MCRSCore(cfg)
    core.seed(4)
    result = core.reset()
    actions = torch.Generator().manual_seed(0)
    start = core.target_pos.clone()
    for _ in range(cfg.max_steps):
        mask = result.action_mask.float().view(-1, 8)
        result = core.step(mask.multinomial(1, generator=actions).view(16, cfg.n_uavs))
        cells = core.target_pos[..., 0] * cfg.height + core.target_pos[..., 1]
        no_fly = core.no_fly_pos[..., 0] * cfg.height + core.no_fly_pos[..., 1]
        assert (cells.sort(-1).values.diff(dim=-1) > 0).all()  # distinct cells
        assert not (cells.unsqueeze(-1) == no_fly.unsqueeze(-2)).any()
        assert torch.equal(core.is_target.sum(-1), torch.full((16,), cfg.n_targets))
        found = (result.state_map[:, 1].reshape(16, -1).gather(1, cells) >= cfg.target_threshold).sum(-1)
        assert torch.equal(result.metrics["targets_found"], found.float())
    assert (core.target_pos != start).any()


#: What each variant preset changes from map20 (docs/ENVIRONMENT.md lists the same values).
PRESET_CHANGES = {
    "map20_delay": {"comm_delay": 3},
    "map20_bandwidth": {"comm_budget": 4},
    "map20_dynamic": {"target_motion": "random_walk", "target_move_prob": 0.05, "evidence_decay": 0.02},
}


@pytest.mark.parametrize("preset", sorted(PRESET_CHANGES))
def test_variant_presets_are_map20_with_the_documented_changes(preset):
    assert scenario(preset) == scenario("map20").replace(name=preset, **PRESET_CHANGES[preset])


@pytest.mark.parametrize("preset", sorted(PRESET_CHANGES))
def test_torchrl_specs_hold_under_each_variant(preset):
    env = MCRSEnv(preset, num_envs=3, max_steps=12, expose_beliefs=True)
    env.set_seed(0)
    check_env_specs(env)
    expected = torch.float32 if scenario(preset).evidence_decay > 0 else torch.int16
    assert env.rollout(5).get(("next", "state_counts")).dtype == expected


def test_paper_defaults_hold_no_variant_state():
    """Defaults are the paper: no channel, walk or decay objects, and the same state bytes as before."""
    core = MCRSCore(scenario("map20", num_envs=4))
    assert core.channel is None and core.walk is None and core.decay is None and core.found_once is None
    variants = MCRSCore(scenario("map20_dynamic", num_envs=4).replace(comm_delay=2, comm_budget=4))
    assert variants.state_nbytes() > core.state_nbytes()
