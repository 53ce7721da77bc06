"""The run's text log: ``train.log`` / ``evaluate.log`` hold what the run did, without colour codes; the
console shows warnings above the progress bar; TorchRL's INFO line on building the replay stays quiet."""

from __future__ import annotations

import logging
import logging.config
import re
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import mcrs.evaluate  # noqa: F401 (registers the mcrs-eval schema)
from mcrs.experiment.commands.console import ANSI, PlainFormatter, TqdmHandler
from mcrs.experiment.run import logging as run_logging
from mcrs.experiment.run.logging import PlainProgress, log_event, progress_bar
from mcrs.experiment.training.trainer import Experiment
from mcrs.train import CONFIG_DIR
from tests.train_helpers import compose_config


@pytest.fixture
def restore_logging():
    """dictConfig reconfigures the root and torchrl loggers: put them back for the other tests."""
    root, torchrl = logging.getLogger(), logging.getLogger("torchrl")
    saved = (root.level, root.handlers[:], torchrl.level, torchrl.handlers[:], torchrl.propagate)
    yield
    for h in root.handlers:
        if h not in saved[1]:
            h.close()
    root.setLevel(saved[0])
    root.handlers[:] = saved[1]
    torchrl.setLevel(saved[2])
    torchrl.handlers[:] = saved[3]
    torchrl.propagate = saved[4]


def _job_logging(config_name: str, run_dir: Path) -> dict:
    """The job-logging config Hydra applies for ``config_name``, resolved for ``run_dir``."""
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(
            config_name=config_name,
            return_hydra_config=True,
            overrides=["algo=qmix"] if config_name == "config" else [],
        )
    cfg.hydra.runtime.output_dir = str(run_dir)
    cfg.hydra.job.name = config_name
    return OmegaConf.to_container(cfg.hydra.job_logging, resolve=True)


def test_plain_formatter_strips_torchrl_colour_codes() -> None:
    from torchrl._utils import _CustomFormatter

    record = logging.LogRecord("torchrl", logging.WARNING, __file__, 1, "replay built", None, None)
    coloured = _CustomFormatter().format(record)
    assert "\x1b[" in coloured
    plain = PlainFormatter("%(name)s %(message)s").format(record)
    assert plain == "torchrl replay built" and not ANSI.search(PlainFormatter("%(message)s").format(
        logging.LogRecord("x", logging.INFO, __file__, 1, "\x1b[92mgreen\x1b[0m", None, None)))  # fmt: skip


def test_the_job_log_gets_every_record_plain_and_the_console_only_warnings(
    tmp_path: Path, restore_logging, capfd: pytest.CaptureFixture
) -> None:
    for config_name in ("config", "eval"):
        logging.config.dictConfig(_job_logging(config_name, tmp_path))
        log_event("evaluation at env step 0")
        logging.getLogger("torchrl").info("Initialized LazyTensorStorage")  # TorchRL's noise: nowhere
        logging.getLogger("torchrl").warning("\x1b[92ma torchrl warning\x1b[0m")
        logging.getLogger("mcrs.train").error("diverged", extra={"console": False})  # the CLI prints it
        for h in logging.getLogger().handlers:
            h.flush()
        text = (tmp_path / f"{config_name}.log").read_text()
        assert "[mcrs.run][INFO] evaluation at env step 0" in text
        assert "[torchrl][WARNING] a torchrl warning" in text and "diverged" in text
        assert "LazyTensorStorage" not in text and "\x1b" not in text
        out, err = capfd.readouterr()
        assert out == "" and err == "torchrl: WARNING: a torchrl warning\n", (out, err)


def test_tqdm_handler_writes_above_the_bar_and_skips_console_false(capsys: pytest.CaptureFixture) -> None:
    from tqdm import tqdm

    handler = TqdmHandler(sys.stderr)
    logger = logging.getLogger("mcrs.test_tqdm_handler")
    logger.addHandler(handler)
    logger.propagate = False
    try:
        with tqdm(total=10, file=sys.stderr, disable=False) as bar:
            logger.warning("shown")
            logger.warning("hidden", extra={"console": False})
            bar.update(5)
    finally:
        logger.removeHandler(handler)
    err = capsys.readouterr().err
    assert "shown\n" in err and "hidden" not in err


def test_training_keeps_torchrl_info_lines_off_the_console(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """TorchRL logs ``Initialized LazyTensorStorage ...`` at INFO when the replay is first filled; in a run
    it is not emitted (so it cannot break the progress bar), unless ``RL_LOGGING_LEVEL`` asks for it."""

    class Keep(logging.Handler):
        def __init__(self) -> None:
            super().__init__(logging.DEBUG)
            self.messages: list[str] = []

        def emit(self, record: logging.LogRecord) -> None:
            self.messages.append(record.getMessage())

    monkeypatch.delenv("RL_LOGGING_LEVEL", raising=False)
    torchrl, keep = logging.getLogger("torchrl"), Keep()
    monkeypatch.setattr(torchrl, "level", logging.INFO)
    monkeypatch.setattr(torchrl, "handlers", [keep])
    Experiment(compose_config("train.total_env_steps=20"), tmp_path / "run").run()
    assert not any("LazyTensorStorage" in m for m in keep.messages), keep.messages
    assert torchrl.level == logging.WARNING
    torchrl.setLevel(logging.INFO)  # a new process: a resume loads the replay before the logger is made
    Experiment(compose_config("train.total_env_steps=40"), tmp_path / "run", resume=True).run()
    assert not any("LazyTensorStorage" in m for m in keep.messages), keep.messages

    monkeypatch.setenv("RL_LOGGING_LEVEL", "INFO")  # TorchRL's own switch brings them back
    torchrl.setLevel(logging.INFO)
    Experiment(compose_config("train.total_env_steps=20"), tmp_path / "again").run()
    assert any("LazyTensorStorage" in m for m in keep.messages), keep.messages


def test_progress_without_a_terminal_is_plain_lines_with_the_eta_and_the_latest_evaluation(
    capsys: pytest.CaptureFixture,
) -> None:
    """Under nohup or into a log file (stderr no terminal: capsys's) a bar would print nothing readable:
    the progress is a line when it starts, one per interval, and one when it ends."""
    bar = progress_bar(2_000_000, 0, True, "qmix map20", interval=0.0)
    assert isinstance(bar, PlainProgress)
    bar.set_postfix({"eps": "0.050", "eval_reward": "12.3"}, refresh=False)
    bar.update(120_000)
    bar.close()
    bar.close()  # once
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 3, lines
    assert lines[0].startswith("qmix map20: 0/2M steps (0%), elapsed 00:00"), lines
    assert re.fullmatch(
        r"qmix map20: 120k/2M steps \(6%\), [\d.]+[kMG]? steps/s, elapsed [\d:]+, ETA [\d:]+, eps=0.050, "
        r"eval_reward=12.3",
        lines[1],
    ), lines


def test_the_bars_last_line_shows_the_final_evaluation(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    config = compose_config("train.total_env_steps=60", "logger.progress_bar=true")
    result = Experiment(config, tmp_path / "run").run()
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.endswith(f"eval_reward={result['episode_reward']:.1f}"), last


def test_plain_progress_waits_its_interval_and_a_disabled_bar_prints_nothing(
    capsys: pytest.CaptureFixture,
) -> None:
    with progress_bar(100, 40, True, "resumed", interval=3600.0) as bar:  # a resumed run starts at 40
        for _ in range(6):
            bar.update(10)
    lines = capsys.readouterr().err.splitlines()
    assert [line.split(",")[0] for line in lines] == [
        "resumed: 40/100 steps (40%)",
        "resumed: 100/100 steps (100%)",
    ]
    with progress_bar(100, 0, False, "off") as bar:  # logger.progress_bar=false: the campaign's children
        bar.update(100)
    assert capsys.readouterr().err == ""


def test_a_terminal_gets_tqdms_bar_unless_the_job_shares_it(monkeypatch: pytest.MonkeyPatch) -> None:
    from tqdm import tqdm

    monkeypatch.setattr(run_logging, "_is_terminal", lambda stream: True)
    bar = progress_bar(100, 0, False, "terminal")
    assert isinstance(bar, tqdm)
    bar.close()
    assert not run_logging.parallel_sweep_job()  # not in a Hydra job
    monkeypatch.setattr(run_logging, "parallel_sweep_job", lambda: True)  # a joblib/Ray/Slurm sweep job
    assert isinstance(progress_bar(100, 0, True, "job", interval=3600.0), PlainProgress)
