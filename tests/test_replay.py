"""Whole episodes in the replay buffer: the episode layout and the buffer's saved state."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import TransformedEnv

from mcrs.env import MCRSEnv
from mcrs.experiment.run.replay_store import load_replay_state_dict, replay_state_dict
from mcrs.experiment.training.replay import episodes_from_rollout, make_episode_buffer
from mcrs.models.acting import make_acting_policy, recurrent_primer
from mcrs.models.agent import RecurrentAgent

T = 7


@pytest.fixture(scope="module")
def batch():
    env = MCRSEnv("map10", num_envs=3, max_steps=T)
    c = env.config
    env = TransformedEnv(env, recurrent_primer(3, c.n_uavs, 8))
    _, exploring, _ = make_acting_policy(RecurrentAgent(c.obs_dim, 8, c.n_uavs, hidden_dim=8), 8)
    collector = Collector(
        env, exploring, frames_per_batch=3 * T, total_frames=-1, trust_policy=True,
        auto_register_policy_transforms=False,
    )  # fmt: skip
    out = next(iter(collector))
    collector.shutdown()
    return out


def test_episode_layout(batch) -> None:
    ep = episodes_from_rollout(batch)
    assert ep.batch_size == (3, T + 1)
    obs = ep["agents", "observation"]
    assert torch.equal(obs[:, :T], batch["agents", "observation"])
    assert torch.equal(obs[:, T], batch["next", "agents", "observation"][:, -1])
    assert torch.equal(ep["state"][:, 1:T], batch["next", "state"][:, :-1])
    assert torch.equal(ep["reward"][:, :T], batch["next", "reward"])
    assert torch.equal(ep["agents", "action"][:, :T], batch["agents", "action"])
    assert ep["filled"][:, :T].all() and not ep["filled"][:, T].any()
    assert ep["done"][:, T - 1].all() and not ep["done"][:, : T - 1].any()
    assert ("agents", "rnn_hidden") not in ep.keys(include_nested=True)  # acting state is not stored


def test_time_limit_terminal_marks_the_horizon_terminated(batch) -> None:
    bootstrapped = episodes_from_rollout(batch, time_limit="bootstrap")
    terminal = episodes_from_rollout(batch, time_limit="terminal")
    assert not bootstrapped["terminated"].any()  # MCRS episodes end by the time limit only: truncated
    assert terminal["terminated"][:, T - 1].all() and not terminal["terminated"][:, : T - 1].any()
    assert not terminal["terminated"][:, T].any()  # the padding row is never a transition
    assert torch.equal(terminal["done"], bootstrapped["done"])
    # A feed-forward cut (whole_episodes=False) is not a time limit: it is never terminal.
    cut = episodes_from_rollout(batch[:, : T - 2], whole_episodes=False, time_limit="terminal")
    assert not cut["terminated"].any()
    with pytest.raises(ValueError, match=r"time_limit='never': must be one of \['terminal', 'bootstrap'\]"):
        episodes_from_rollout(batch, time_limit="never")


def test_misaligned_batches_are_refused(batch) -> None:
    with pytest.raises(ValueError, match="frames_per_batch"):
        episodes_from_rollout(batch[:, :-1])
    with pytest.raises(ValueError, match="reset"):
        episodes_from_rollout(batch[:, 1:])
    with pytest.raises(ValueError, match="batch_size"):
        episodes_from_rollout(batch[0])


def test_buffer_samples_whole_episodes_and_caps(batch) -> None:
    buffer = make_episode_buffer(capacity=5, batch_size=4)
    for _ in range(3):
        buffer.extend(episodes_from_rollout(batch))
    assert len(buffer) == 5  # 9 episodes written, the oldest overwritten
    assert buffer.sample().batch_size == (4, T + 1)
    with pytest.raises(ValueError, match="capacity"):
        make_episode_buffer(0, 1)


def test_replay_state_round_trip_after_wrap_around() -> None:
    buffer = make_episode_buffer(capacity=4, batch_size=2)
    for i in range(6):
        buffer.extend(
            TensorDict({"x": torch.full((1, 3), float(i)), ("a", "b"): torch.ones(1, 3, 2)}, [1, 3])
        )
    state = replay_state_dict(buffer)
    restored = make_episode_buffer(capacity=4, batch_size=2)
    load_replay_state_dict(restored, state)
    assert len(restored) == 4
    assert torch.equal(restored[:4]["x"], buffer[:4]["x"])
    for i in (6, 7):  # the next writes land on the same slots
        item = TensorDict({"x": torch.full((1, 3), float(i)), ("a", "b"): torch.ones(1, 3, 2)}, [1, 3])
        buffer.extend(item)
        restored.extend(item.clone())
    assert torch.equal(restored[:4]["x"], buffer[:4]["x"])
    assert state["episodes"]["x"].shape[0] == 4  # only the filled part is saved


def test_empty_replay_state() -> None:
    restored = make_episode_buffer(capacity=4, batch_size=2)
    load_replay_state_dict(restored, replay_state_dict(make_episode_buffer(capacity=4, batch_size=2)))
    assert len(restored) == 0


def test_the_saved_format_is_the_one_checkpoints_already_hold() -> None:
    """Flat ``"a/b"`` keys and the filled episodes only: a replay saved by earlier versions (whose keys
    were joined by hand) still loads, and a save writes the same keys."""
    episodes = TensorDict({"x": torch.arange(6.0).view(2, 3), ("a", "b"): torch.ones(2, 3, 2)}, [2, 3])
    written = make_episode_buffer(capacity=4, batch_size=2)
    written.extend(episodes)
    saved = {
        "length": 2,
        "writer": written.writer.state_dict(),
        "batch_size": [2, 3],
        "episodes": {"x": episodes["x"].clone(), "a/b": episodes["a", "b"].clone()},
    }
    state = replay_state_dict(written)
    assert sorted(state["episodes"]) == ["a/b", "x"] and state["batch_size"] == [2, 3]
    restored = make_episode_buffer(capacity=4, batch_size=2)
    load_replay_state_dict(restored, saved)
    assert len(restored) == 2 and torch.equal(restored[:2]["a", "b"], episodes["a", "b"])
    assert torch.equal(restored[:2]["x"], episodes["x"])
