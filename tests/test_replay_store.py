"""Incremental replay checkpoints: only changed blocks are written, a crash mid-save keeps the previous
checkpoint whole, a reload restores the same slots and write position, and time-based checkpoints run."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run.replay_store import ReplayStore
from mcrs.experiment.training.replay import make_episode_buffer
from mcrs.experiment.training.trainer import Experiment
from tests.train_helpers import compose_config


def episodes(first: int, n: int) -> TensorDict:
    """``n`` distinguishable episodes ``[n, 3]`` numbered from ``first``."""
    ids = torch.arange(first, first + n, dtype=torch.float32)
    return TensorDict(
        {
            "reward": ids[:, None, None].expand(n, 3, 1).clone(),
            ("agents", "action"): torch.zeros(n, 3, 2).long(),
        },
        batch_size=[n, 3],
    )


def block_files(directory: Path) -> set[str]:
    return {p.name for p in directory.glob("replay_*.pt")}


def stored_ids(buffer) -> list[int]:
    return buffer.storage.get(torch.arange(len(buffer))).get("reward")[:, 0, 0].long().tolist()


def reloaded(directory: Path, manifest: dict, capacity: int = 10):
    buffer = make_episode_buffer(capacity, 2)
    ReplayStore(directory, block_episodes=4).load(buffer, manifest)
    return buffer


def test_only_the_blocks_written_since_the_last_save_are_rewritten(tmp_path: Path) -> None:
    buffer, store = make_episode_buffer(10, 2), ReplayStore(tmp_path, block_episodes=4)
    store.mark_written(buffer.extend(episodes(0, 6)))  # slots 0-5: blocks 0 and 1
    first = store.save(buffer)
    store.commit()
    assert first["files"] == ["replay_00000_000001.pt", "replay_00001_000001.pt"]
    store.mark_written(buffer.extend(episodes(6, 3)))  # slots 6-8: blocks 1 and 2
    second = store.save(buffer)
    assert second["files"] == ["replay_00000_000001.pt", "replay_00001_000002.pt", "replay_00002_000002.pt"]
    # A crash before last.pt names the new manifest: the previous one is still complete on disk.
    assert stored_ids(reloaded(tmp_path, first)) == [0, 1, 2, 3, 4, 5]
    store.commit()  # last.pt now names the second manifest: the replaced block file goes
    assert block_files(tmp_path) == set(second["files"])
    # Wrapping around the ring: slots 9, 0, 1, 2 (blocks 2 and 0); block 1 stays as it was.
    store.mark_written(buffer.extend(episodes(9, 4)))
    third = store.save(buffer)
    store.commit()
    assert third["files"][1] == second["files"][1] and third["files"][0] != second["files"][0]
    again = reloaded(tmp_path, third)
    assert stored_ids(again) == stored_ids(buffer) == [10, 11, 12, 3, 4, 5, 6, 7, 8, 9]
    assert again.writer.state_dict() == buffer.writer.state_dict()
    store.mark_written(again.extend(episodes(13, 1)))  # the next write goes to the same slot in both
    buffer.extend(episodes(13, 1))
    assert stored_ids(again) == stored_ids(buffer)


def test_a_manifest_that_does_not_match_its_files_is_refused(tmp_path: Path) -> None:
    buffer, store = make_episode_buffer(10, 2), ReplayStore(tmp_path, block_episodes=4)
    store.mark_written(buffer.extend(episodes(0, 5)))
    manifest = store.save(buffer)
    with pytest.raises(ckpt.CheckpointError, match="hold 5 episodes, the manifest 7"):
        reloaded(tmp_path, {**manifest, "length": 7})
    with pytest.raises(ckpt.CheckpointError, match="blocks of 3 episodes, this run 4"):
        reloaded(tmp_path, {**manifest, "block_episodes": 3})
    (tmp_path / manifest["files"][1]).unlink()
    with pytest.raises(ckpt.CheckpointError, match="does not exist"):
        reloaded(tmp_path, manifest)


@pytest.mark.slow
def test_time_based_checkpoints_and_the_replay_beside_last_pt(tmp_path: Path) -> None:
    # No step-based checkpoint before the end; a time interval that every batch exceeds.
    cfg = compose_config("train.total_env_steps=120", "train.checkpoint_interval=1000000",
                         "train.checkpoint_minutes=1e-9")  # fmt: skip
    Experiment(cfg, tmp_path).run()
    saved = sorted(p.name for p in (tmp_path / "checkpoints").glob("model_*.pt"))
    assert saved == [f"model_{s:09d}.pt" for s in (40, 80, 120)]
    state = ckpt.load(ckpt.checkpoint_path(tmp_path))
    assert "replay" not in state and state["replay_blocks"]["length"] == 12
    assert block_files(tmp_path / "checkpoints") == set(state["replay_blocks"]["files"])


def test_bad_checkpoint_minutes_is_refused(tmp_path: Path) -> None:
    from mcrs.experiment.config import ConfigError

    with pytest.raises(ConfigError, match=r"train\.checkpoint_minutes=-1\.0: must be >= 0"):
        Experiment(compose_config("train.checkpoint_minutes=-1"), tmp_path)
