"""Evaluation videos reach the loggers (TensorBoard, wandb offline), and ``mcrs-report`` reads the runs
of every logger: tiny training runs, read back through the loggers' own file readers."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from PIL import Image

from mcrs.experiment.config import compose
from mcrs.experiment.training.trainer import Experiment
from tests.train_helpers import TINY, TINY_MEMORY

pytestmark = pytest.mark.slow

#: Two evaluations (at 0 and at the end) of 10-step episodes.
STEPS, T = 40, 10


def tiny_run(run_dir: Path, *overrides: str) -> Path:
    Experiment(compose("algo=qmix", *TINY, f"train.total_env_steps={STEPS}", *overrides), run_dir).run()
    return run_dir


def gif_frames(data: bytes) -> tuple[int, tuple[int, int]]:
    image = Image.open(io.BytesIO(data))
    return image.n_frames, image.size


def test_evaluation_video_reaches_a_tensorboard_run(tmp_path: Path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import IMAGES, EventAccumulator

    run = tiny_run(tmp_path / "tb", "logger=tensorboard", "logger.video=true")
    events = EventAccumulator(str(run / "logs"), size_guidance={IMAGES: 0})
    events.Reload()
    assert "eval/video" in events.Tags()["images"]
    videos = events.Images("eval/video")
    assert [v.step for v in videos] == [0, STEPS]  # one greedy episode per evaluation
    for video in videos:
        data = video.encoded_image_string
        assert data[:6] == b"GIF89a"
        frames, size = gif_frames(data)
        assert frames == T + 1 and size == (video.width, video.height)  # reset to the time limit
    # The same GIFs beside the run, whatever the backend.
    assert sorted(p.name for p in (run / "videos").iterdir()) == [
        "eval_video_0.gif",
        f"eval_video_{STEPS}.gif",
    ]
    assert (run / "videos" / f"eval_video_{STEPS}.gif").read_bytes() == videos[-1].encoded_image_string


def test_evaluation_video_reaches_an_offline_wandb_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("WANDB_MODE", "offline")
    run = tiny_run(tmp_path / "wb", "logger=wandb", "logger.video=true")
    media = sorted((run / "wandb").glob("offline-run-*/files/media/videos/eval/video_*.gif"))
    assert len(media) == 2
    assert gif_frames(media[0].read_bytes())[0] == T + 1


def test_report_reads_the_runs_of_every_logger_alike(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The same seed and config logged by csv, tensorboard and wandb (offline): ``mcrs-report`` finds all
    three (none skipped), reads the same evaluations from each, and exports them for marl-eval."""
    import json

    import numpy as np

    from mcrs_lab.analysis.report import main as report_main
    from mcrs_lab.analysis.runs import find_runs

    monkeypatch.setenv("WANDB_MODE", "offline")
    for backend in ("csv", "tensorboard", "wandb"):
        tiny_run(tmp_path / backend, f"logger={backend}")
    assert not (tmp_path / "csv" / "videos").exists()  # video is off by default
    runs = find_runs([tmp_path])
    assert runs.skipped == [] and len(runs.training) == 3
    series = {run.path.name: run.scalar("eval/episode_reward") for run in runs.training}
    steps, values = series["csv"]
    assert steps.tolist() == [0, STEPS]
    for backend in ("tensorboard", "wandb"):
        assert series[backend][0].tolist() == [0, STEPS]
        np.testing.assert_allclose(series[backend][1], values, rtol=1e-6)  # TensorBoard keeps float32
    out = tmp_path / "report"
    assert report_main([str(tmp_path), "--out", str(out), "--marl-eval", str(out / "marl_eval.json")]) == 0
    assert "3 training runs and 0 evaluation results read; 0 skipped" in (out / "report.md").read_text()
    runs_json = json.loads((out / "marl_eval.json").read_text())["mcrs"]["map10"]["qmix"]
    assert len(runs_json) == 3
    for run in runs_json.values():
        assert [run[f"step_{i}"]["step_count"] for i in range(2)] == [0, STEPS]
        assert run["absolute_metrics"]["episode_reward"][0] == pytest.approx(values[-1], rel=1e-6)


#: The scalars of the episodic memory and of the curiosity: an algorithm without them must not log them.
MEMORY_SCALARS = ("train/memory_hit_rate", "train/loss_memory", "train/memory_target_mean",
                  "train/incentive_mean", "train/intrinsic_mean")  # fmt: skip


def _logged(run: Path) -> set[str]:
    root = run / "logs" / "scalars"
    return {p.relative_to(root).with_suffix("").as_posix() for p in root.rglob("*.csv")}


def test_scalars_that_do_not_apply_to_an_algorithm_are_not_logged(tmp_path: Path) -> None:
    """QMIX has no memory and no curiosity: none of their scalars (each would read 0 at every row); EMU
    logs its memory's and its incentive's, not those of the memory target it does not train (lambda 0)."""
    qmix = _logged(tiny_run(tmp_path / "qmix"))
    assert not [n for n in qmix if n.startswith(("memory/", "curiosity/")) or n in MEMORY_SCALARS], qmix
    assert {"train/loss_td", "train/q_taken_mean", "eval/episode_reward", "eval/no_fly_violations"} <= qmix
    emu = _logged(tiny_run(tmp_path / "emu", "algo=emu", *TINY_MEMORY))
    assert {"train/memory_hit_rate", "train/incentive_mean", "memory/size", "memory/lookup_hit_rate"} <= emu
    assert not {"train/loss_memory", "train/memory_target_mean", "train/intrinsic_mean"} & emu
    assert emu - qmix >= {"train/memory_hit_rate", "train/incentive_mean"}
