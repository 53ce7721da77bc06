"""The reward ledger (python -m mcrs_lab.analysis.ledger): its sums are the env's, its charges are r3's."""

from __future__ import annotations

import pytest
import torch

from mcrs.env.config import scenario
from mcrs.env.core import MOVES
from mcrs.evaluate import episode_metrics
from mcrs.policies import POLICIES
from mcrs.policies.base import ACTION_MASK, OBSERVATION, Policy
from mcrs_lab.analysis.ledger import main, play, policy_labels

EPISODES = 8


@pytest.mark.parametrize("policy", ["random", "lawnmower"])
def test_terms_sum_to_the_episode_reward_and_r3_is_the_charges(policy: str) -> None:
    config = scenario("map10")
    ledger = play(config, policy, EPISODES, seed=3)
    reward = episode_metrics(config, policy, EPISODES, seed=3)["episode_reward"]
    torch.testing.assert_close(ledger.reward, reward, rtol=0, atol=1e-3)
    charges = ledger.charged_first + ledger.charged_read
    assert charges.sum() > 0  # both policies enter zones on map10
    torch.testing.assert_close(charges * config.w_no_fly, -ledger.terms[:, 2])
    assert bool((ledger.charged_avoidable <= charges).all())
    # r1 gathered so far never falls (every reading lowers the uncertainty) and ends at the total
    r1 = torch.cat([ledger.r1_by, ledger.terms[:, :1]], dim=1)
    assert bool((r1.diff(dim=1) >= -1e-6).all())


def test_the_shield_leaves_no_charge() -> None:
    ledger = play(scenario("map10", no_fly_shield=True), "random", EPISODES, seed=0)
    assert float(ledger.terms[:, 2].abs().sum()) == 0.0
    assert float((ledger.charged_first + ledger.charged_read).sum()) == 0.0


def test_a_lone_greedy_reader_never_rereads_and_a_random_walker_does() -> None:
    # One UAV, zones masked: greedy takes the allowed move of largest own m(U), so it moves onto a read
    # cell only when no unread one is allowed; a random walker wastes moves, more of them late.
    config = scenario("map10", n_uavs=1, no_fly_shield=True)
    greedy = play(config, "greedy", EPISODES, seed=2)
    assert float(greedy.rereads.sum()) == 0.0
    walker = play(config, "random", EPISODES, seed=2)
    assert bool((walker.rereads.sum(1) > 0).all())
    assert float(walker.rereads[:, 1].sum()) > float(walker.rereads[:, 0].sum())
    # Stranded steps (no unread cell next) and rereads never overlap, and the map runs out of unread cells
    # late: a lone greedy UAV on map10 is stranded more in the second half than in the first.
    assert bool((walker.stranded + walker.rereads <= config.max_steps / 2).all())
    assert float(greedy.stranded[:, 1].sum()) > float(greedy.stranded[:, 0].sum())
    # Stranded, greedy still takes the largest own m(U) it may (alone, nothing else pulls it): it gives up
    # none; the random walker gives up some, at most 1 (a whole m(U)) per stranded step.
    assert float(greedy.given_up.abs().sum()) < 1e-6
    assert float(walker.given_up.sum()) > 0
    assert bool((walker.given_up >= 0).all() and (walker.given_up <= walker.stranded).all())


class ZoneSeeker(Policy):
    """One UAV that walks onto the visible zone, steps off it (its first allowed move) and back on."""

    def act(self, tensordict):
        obs, mask = tensordict.get(OBSERVATION), tensordict.get(ACTION_MASK)
        offset, visible = self.layout.relative_cells(self.layout.no_fly_features(obs))  # [E, N, Z, 2]
        moves = torch.tensor(MOVES)
        gap = (offset[..., :1, :] - moves).abs().amax(-1)  # [E, N, 8]: Chebyshev distance after each move
        toward = gap.masked_fill(~mask, 10**6).argmin(-1)
        first_allowed = mask.to(torch.int64).argmax(-1)
        return torch.where(visible[..., 0], toward, first_allowed)


@pytest.mark.parametrize("prior", ["unknown", "known"])
def test_a_zone_is_charged_as_unread_once_then_as_read(monkeypatch: pytest.MonkeyPatch, prior: str) -> None:
    """An unread zone's first entry buys a reading; a known zone (the paper's reading) buys nothing."""
    config = scenario(
        "map10", width=5, height=5, n_uavs=1, n_no_fly=1, n_targets=1, sight_range=8.0, max_steps=12,
        no_fly_prior=prior,
    )  # fmt: skip
    monkeypatch.setitem(POLICIES, "zone_seeker", ZoneSeeker)
    ledger = play(config, "zone_seeker", 4, seed=1)
    charges = ledger.charged_first + ledger.charged_read
    assert bool((charges >= 4).all())  # it reaches the zone within 4 steps, then enters every other step
    first = 1.0 if prior == "unknown" else 0.0
    assert ledger.charged_first.tolist() == [first] * 4
    torch.testing.assert_close(ledger.charged_read, charges - first)
    torch.testing.assert_close(charges * config.w_no_fly, -ledger.terms[:, 2])


def test_the_command_prints_one_row_per_policy(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--env", "map10", "--episodes", "2", "--policy", "greedy", "--policy", "coverage"]) == 0
    out = capsys.readouterr().out
    assert "safety_rule=enter, discovery_rule=belief, no_fly_view=blocked, no_fly_prior=known, " in out
    assert "no_fly_shield=false, uav_shield=false" in out
    rows = [line for line in out.splitlines() if line.startswith("| greedy") or line.startswith("| coverage")]
    assert len(rows) == 2


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--episodes", "0"], "--episodes=0: must be in [1, 4096]"),
        (["--policy", "nonsense"], "--policy=nonsense: unknown policy 'nonsense'"),
        (["--policy", "/no/such/run"], "--policy=/no/such/run:"),
    ],
)
def test_bad_arguments_are_one_line(argv: list[str], message: str) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--env", "map10", *argv])
    assert message in str(exit_info.value)


def test_checkpoints_of_the_same_name_get_rows_of_their_own() -> None:
    """Two runs' ``model_000800000.pt`` were one row (the second overwrote the first): each label now takes
    as many parent folders as it needs to be told apart."""
    names = [
        "greedy",
        "out/a/checkpoints/model_000800000.pt",
        "out/b/checkpoints/model_000800000.pt",
        "out/c/checkpoints/model_000700000.pt",
        "runs/map20_qmix_seed0",
    ]
    assert policy_labels(names) == [
        "greedy",
        "a/checkpoints/model_000800000.pt",
        "b/checkpoints/model_000800000.pt",
        "model_000700000.pt",
        "map20_qmix_seed0",
    ]
    assert policy_labels(["greedy", "greedy"]) == [
        "greedy",
        "greedy",
    ]  # the same policy twice: nothing to tell
