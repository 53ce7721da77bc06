"""Bad inputs for the research tools (issue 33): mcrs-campaign, mcrs-report, mcrs-results, mcrs-eval's
checkpoints and a run's files, tried as a hostile user would.

Each case marked ``bad_tool_input`` is one bad input: a campaign file, a command-line value, a record, a
log, a run's config.yaml, a checkpoint or a document block. Each must be refused with one line naming
the file or the field (no traceback, nothing accepted silently, nothing written or removed outside the
tool's root). ``pytest -m bad_tool_input tests/test_bad_inputs_tools.py`` runs exactly them; README.md
and docs/RELIABILITY.md state their number ("N bad tool inputs"), checked by
``test_the_documented_tool_count_is_the_suites``.
"""

from __future__ import annotations

import copy
import json
import re
import time
import tracemalloc
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from mcrs.experiment.config import ConfigError, validate
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run.rundir import RunLock
from mcrs.experiment.util.untrusted import MAX_YAML_BYTES
from mcrs.train import _read_run_config
from mcrs_lab.analysis.doc_tables import main as results_main
from mcrs_lab.analysis.record_schema import RECORD_FORMAT, RECORD_VERSION, RecordError
from mcrs_lab.analysis.records import make_record, training_record_path
from mcrs_lab.analysis.report import main as report_main
from mcrs_lab.analysis.runs import find_runs, read_record
from mcrs_lab.campaign.cli import main as campaign_main
from mcrs_lab.campaign.evaluations import Evaluation, EvaluationJob, run_job
from mcrs_lab.campaign.matrix import load_matrix
from mcrs_lab.campaign.progress import Progress
from mcrs_lab.campaign.runner import LOG, Campaign
from tests.train_helpers import compose_config

# ------------------------------------------------------------------------------------ campaign files
POINTS = """
budget: smoke
seeds: [0]
figures:
  figa:
    experiment: comm_range
    env: [map10]
    algo: [qmix]
    sweep: {env.comm_range: [0, 2]}
"""
EVALUATION = """
evaluations:
  shield:
    of: [figa]
    heuristics: [greedy]
    episodes: 2
    seeds: [0, 1]
    variants:
      "on": [env.no_fly_shield=true]
"""
ALIAS_BOMB = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + k)}: &{chr(98 + k)} [*{chr(97 + k)}, *{chr(97 + k)}, *{chr(97 + k)}, *{chr(97 + k)}, "
    f"*{chr(97 + k)}, *{chr(97 + k)}, *{chr(97 + k)}, *{chr(97 + k)}, *{chr(97 + k)}, *{chr(97 + k)}]\n"
    for k in range(8)
)  # 9 levels of 10: 10^9 strings once expanded, 700 bytes unexpanded
DEEP = "x: " + "[" * 200 + "]" * 200 + "\n"

#: Overrides a campaign file may not pass on (to mcrs-train, or to mcrs-eval in an evaluation's variants):
#: config values only, never Hydra's settings, the run's identity or a path. Each a bad input.
BAD_CAMPAIGN_OVERRIDES: list[tuple[str, str]] = [
    (POINTS + "overrides: {all: ['+hydra.callbacks.x._target_=builtins.open']}\n", "overrides all: +hydra.callbacks.x._target_=builtins.open: a Hydra setting"),
    (POINTS + "overrides: {all: ['hydra.output_subdir=../../../..']}\n", "overrides all: hydra.output_subdir=../../../..: a Hydra setting"),
    (POINTS + "overrides: {qmix: ['~hydra.callbacks.run_dir_check']}\n", "overrides qmix: ~hydra.callbacks.run_dir_check: a Hydra setting"),
    (POINTS + "overrides: {all: ['hydra.job_logging.handlers.file.filename=/tmp/x.log']}\n", "a Hydra setting"),
    (POINTS + "overrides: {all: ['hydra/launcher=joblib']}\n", "overrides all: hydra/launcher=joblib: a Hydra setting"),
    (POINTS + "overrides: {all: ['++hydra.run.dir=/tmp']}\n", "overrides all: ++hydra.run.dir=/tmp: a Hydra setting"),
    (POINTS + "overrides: {all: ['resume=/tmp/run']}\n", "resume=/tmp/run: set by the tool for each run"),
    (POINTS + "overrides: {all: ['overwrite=true']}\n", "overwrite=true: set by the tool for each run"),
    (POINTS + "overrides: {all: ['seed=7']}\n", "seed=7: set by the tool for each run"),
    (POINTS + "overrides: {all: ['env=map20']}\n", "env=map20: set by the tool for each run"),
    (POINTS + "overrides: {all: ['env.name=${now:%H-%M}']}\n", "env.name=${now:%H-%M}: an interpolation"),
    (POINTS + "overrides: {all: ['+algo.options.x=../../../etc']}\n", "'../../../etc' names a path"),
    (POINTS + "overrides: {all: ['+algo.options.x=[1, /etc/passwd]']}\n", "'/etc/passwd' names a path"),
    (POINTS + "overrides: {all: ['train.lr=0.1,0.2']}\n", "train.lr=0.1,0.2: a sweep of values"),
    (POINTS + "overrides: {all: [3]}\n", "overrides all: 3"),
    (POINTS + "overrides: {all: ['train.lr']}\n", "'train.lr': not an override key=value"),
    (POINTS + "overrides: [a=1]\n", "overrides: a mapping of 'all' or an algorithm"),
    (POINTS + EVALUATION.replace("[env.no_fly_shield=true]", "['hydra.sweep.dir=/tmp']"), "variant on: hydra.sweep.dir=/tmp: a Hydra setting"),
    (POINTS + EVALUATION.replace("[env.no_fly_shield=true]", "['policy=../../run']"), "variant on: policy=../../run: set by the tool for each run"),
    (POINTS + EVALUATION.replace("[env.no_fly_shield=true]", "['+hydra.callbacks.x._target_=os.remove']"), "a Hydra setting"),
]  # fmt: skip

#: (what the campaign file holds in place of a valid part, the error's text). Each a bad input.
BAD_CAMPAIGN_FILES: list[tuple[str, str]] = [
    (POINTS + EVALUATION.replace("shield:", "'../../..':"), "evaluation name='../../..': must be a plain name"),
    (POINTS + EVALUATION.replace("shield:", "'..':"), "evaluation name='..': must be a plain name"),
    (POINTS + EVALUATION.replace("shield:", "'a/b':"), "evaluation name='a/b': must be a plain name"),
    (POINTS + EVALUATION.replace("shield:", "'.hidden':"), "evaluation name='.hidden'"),
    (POINTS + EVALUATION.replace("shield:", "'/etc':"), "evaluation name='/etc'"),
    (POINTS + EVALUATION.replace('"on":', '"../../x":'), "variant='../../x': must be a plain name"),
    (POINTS + EVALUATION.replace('"on":', '"..":'), "variant='..': must be a plain name"),
    (POINTS + EVALUATION.replace('"on":', '"a/b":'), "variant='a/b'"),
    (POINTS + EVALUATION.replace('"on":', '"":'), "variant=''"),
    (POINTS + EVALUATION.replace('"on":', "on:"), "variant True: not a name"),
    (POINTS + EVALUATION.replace("[greedy]", "[../x]"), "heuristics: '../x': allowed values are"),
    (POINTS + EVALUATION.replace("[greedy]", "[greedyy]"), "heuristics: 'greedyy': allowed values are"),
    (POINTS + EVALUATION.replace("    episodes: 2\n", "    algo: [qtran]\n    episodes: 2\n"), "evaluation shield: algo='qtran': allowed values are"),
    (POINTS + EVALUATION.replace("episodes: 2", "episodes: 0"), "episodes=0: a whole number >= 1"),
    (POINTS + EVALUATION.replace("episodes: 2", "episodes: true"), "episodes=True"),
    (POINTS + EVALUATION.replace("episodes: 2", "episodes: 100000000"), "episodes=100000000"),
    (POINTS + EVALUATION.replace("episodes: 2", "episodes: .nan"), "episodes=nan"),
    (POINTS + EVALUATION.replace("seeds: [0, 1]", "seeds: [-1]"), "seeds=[-1]: whole numbers in"),
    (POINTS + EVALUATION.replace("seeds: [0, 1]", "seeds: [1.5]"), "seeds=[1.5]"),
    (POINTS + EVALUATION.replace("seeds: [0, 1]", "seeds: [true]"), "seeds=[True]"),
    (POINTS + EVALUATION.replace("seeds: [0, 1]", "seeds: [99999999999999999999]"), "seeds=[99999999999999999999]"),
    (POINTS + EVALUATION.replace("of: [figa]", "of: [figz]"), "of=['figz']: name figures of the file"),
    (POINTS + EVALUATION.replace("    episodes: 2\n", "    episodes: 2\n    rm: -rf\n"), "unknown keys ['rm']"),
    (POINTS + "evaluations: [a, b]\n", "evaluations: a mapping"),
    (POINTS.replace("seeds: [0]", "seeds: [-1]"), "seeds: -1 is not a whole number in [0, 2**63 - 1]"),
    (POINTS.replace("seeds: [0]", "seeds: [1.5]"), "seeds: 1.5 is not a whole number"),
    (POINTS.replace("seeds: [0]", "seeds: [true]"), "seeds: True is not a whole number"),
    (POINTS.replace("seeds: [0]", "seeds: [x]"), "seeds: 'x' is not a whole number"),
    (POINTS.replace("seeds: [0]", "seeds: [18446744073709551616]"), "seeds: 18446744073709551616"),
    (POINTS.replace("env: [map10]", "env: [map99]"), "env='map99': allowed values are map10, map15"),
    (POINTS.replace("env: [map10]", "env: ['../map10']"), "env='../map10': must be a plain name"),
    (POINTS.replace("algo: [qmix]", "algo: [qtran]"), "algo='qtran': allowed values are"),
    (POINTS.replace("algo: [qmix]", "algo: ['..']"), "algo='..': must be a plain name"),
    (POINTS.replace("experiment: comm_range", "experiment: '../../x'"), "experiment='../../x': must be a plain"),
    (POINTS.replace("experiment: comm_range", "experiment: fig99"), "experiment='fig99': allowed values are"),
    (POINTS.replace("budget: smoke", "budget: '../smoke'"), "budget='../smoke': must be a plain name"),
    (POINTS.replace("budget: smoke", "budget: huge"), "budget='huge': allowed values are"),
    (POINTS.replace("[0, 2]", "[.nan]"), "sweep env.comm_range=[nan]: numbers only"),
    (POINTS.replace("[0, 2]", "[abc]"), "sweep env.comm_range=['abc']: numbers only"),
    (POINTS.replace("    algo: [qmix]\n", ""), "a mapping with experiment, env and algo"),
    (POINTS.replace("figures:\n  figa:", "figures:\n  figa: 3\n  figb:"), "figure figa: a mapping with"),
    (POINTS.split("figures:")[0] + "figures: 3\n", "figures: a mapping"),
    ("[1, 2]\n", "not a campaign file: a mapping with figures"),
    ("root:x:0:0:root:/root:/bin/bash\n", "not a campaign file"),  # any file, read as a mapping
    (POINTS.replace("figures:", "figure:"), "not a campaign file"),
    (POINTS + "evaluation: {}\n", "unknown keys ['evaluation']; allowed: ['budget', 'evaluations',"),
    ("name: '../../x'\n" + POINTS, "name='../../x': must be a plain name"),  # it names the roots
    ("name: /etc\n" + POINTS, "name='/etc': must be a plain name"),
    ("name: '..'\n" + POINTS, "name='..': must be a plain name"),
    ("name: [a]\n" + POINTS, "name"),
    *BAD_CAMPAIGN_OVERRIDES,
    (ALIAS_BOMB, "holds YAML anchors or aliases"),
    (DEEP, "is nested deeper than 32 levels"),
    ("a: [1, 2\n", "is not a valid config (bad YAML"),
    ("a: !!python/object/apply:os.system ['true']\n", "is not plain YAML data"),
    ("x" * (MAX_YAML_BYTES + 1), "is larger than 1,048,576 bytes"),
]  # fmt: skip


def _campaign_args(tmp_path: Path, text: str) -> list[str]:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(text)
    return ["--matrix", str(matrix), "--outputs", str(tmp_path / "out"), "--records", str(tmp_path / "rec")]


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("text", "expected"), BAD_CAMPAIGN_FILES, ids=range(len(BAD_CAMPAIGN_FILES)))
def test_a_bad_campaign_file_is_one_line(text: str, expected: str, tmp_path: Path) -> None:
    outside = tmp_path / "keep.txt"
    outside.write_text("mine")
    with pytest.raises(SystemExit) as info:
        campaign_main(["evaluate", "--dry-run", *_campaign_args(tmp_path, text)])
    message = str(info.value.code)
    assert message.startswith("mcrs-campaign: error: ") and "\n" not in message, message
    assert expected in message, message
    assert outside.read_text() == "mine" and not (tmp_path / "out").exists()


TSNE_POINTS = (
    POINTS.replace("experiment: comm_range", "experiment: baselines")
    .replace("algo: [qmix]", "algo: [semu, cnn_semu]")
    .replace("    sweep: {env.comm_range: [0, 2]}\n", "")
)
TSNE_ENTRY = """
tsne:
  fig9:
    of: figa
    env: map10
    seed: 0
    memory: cnn_semu
    embeddings: [semu, cnn_semu]
    samples: 50
"""
#: A campaign file's tsne entry (figure 9's records, mcrs_lab.campaign.figure9): each a bad input.
BAD_TSNE_ENTRIES: list[tuple[str, str]] = [
    (TSNE_ENTRY.replace("fig9:", "'../x':"), "tsne name='../x': must be a plain name"),
    (TSNE_ENTRY.replace("of: figa", "of: figz"), "tsne fig9: of='figz': name a figure of the file (figa)"),
    (TSNE_ENTRY.replace("env: map10", "env: map99"), "tsne fig9: env='map99': allowed values are"),
    (TSNE_ENTRY.replace("env: map10", "env: map20"), "memory='cnn_semu': figure figa has no map20 cnn_semu point"),
    (TSNE_ENTRY.replace("seed: 0", "seed: 3"), "memory='cnn_semu': figure figa has no map10 cnn_semu point at seed 3"),
    (TSNE_ENTRY.replace("seed: 0", "seed: -1"), "tsne fig9: seed=-1: a whole number in [0, 2**63 - 1]"),
    (TSNE_ENTRY.replace("memory: cnn_semu", "memory: qtran"), "tsne fig9: memory: algo='qtran': allowed values"),
    (TSNE_ENTRY.replace("[semu, cnn_semu]", "[semu, emc]"), "embeddings='emc': figure figa has no map10 emc point"),
    (TSNE_ENTRY.replace("[semu, cnn_semu]", "[]"), "tsne fig9: embeddings=[]: a list of algorithms"),
    (TSNE_ENTRY.replace("samples: 50", "samples: 1"), "tsne fig9: samples=1: a whole number in [2, 100000]"),
    (TSNE_ENTRY.replace("samples: 50", "samples: 1000000"), "samples=1000000: a whole number in [2, 100000]"),
    (TSNE_ENTRY.replace("    samples: 50\n", "    perplexity: 5\n"), "tsne fig9: unknown keys ['perplexity']"),
    (TSNE_ENTRY.replace("    seed: 0\n", ""), "tsne fig9: missing keys ['seed']"),
    ("tsne: [fig9]\n", "tsne: a mapping of names to entries"),
]  # fmt: skip


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("entry", "expected"), BAD_TSNE_ENTRIES, ids=range(len(BAD_TSNE_ENTRIES)))
def test_a_bad_tsne_entry_is_one_line(entry: str, expected: str, tmp_path: Path) -> None:
    for command in (["tsne"], ["run", "--hours", "1", "--dry-run"]):  # refused before anything runs
        with pytest.raises(SystemExit) as info:
            campaign_main([*command, *_campaign_args(tmp_path, TSNE_POINTS + entry)])
        message = str(info.value.code)
        assert message.startswith("mcrs-campaign: error: ") and "\n" not in message, message
        assert expected in message, message
    assert not (tmp_path / "rec").exists() and not (tmp_path / "out").exists()


def _tsne_record(path: Path, **change: Any) -> Path:
    from mcrs_lab.analysis import tsne

    meta = {"format": tsne.TSNE_FORMAT, "version": tsne.TSNE_VERSION, "env": "map10",
            "panels": [{"name": "raw state", "dims": 3, "locality": 1.0, "locality_tsne": 1.0}]}  # fmt: skip
    arrays = {"xy": np.zeros((1, 4, 2), np.float32), "returns": np.arange(4, dtype=np.float32)}
    for key, value in change.items():
        (arrays if key in arrays else meta)[key] = value
        if value is None:
            (arrays if key in arrays else meta).pop(key)
    return tsne.write_npz_record(path, arrays, meta)


#: (what a t-SNE record holds instead, the error's text): figure 9 drawn from a bad record.
BAD_TSNE_RECORDS: list[tuple[dict[str, Any] | bytes, str]] = [
    (b"not a zip file", "tsne.npz: not a t-SNE record"),
    ({"format": "mcrs-tsne-states"}, "field meta.format: 'mcrs-tsne-states', expected 'mcrs-tsne'"),
    ({"version": 99}, "field meta.version: 99; this mcrs reads 1"),
    ({"returns": None}, "field returns: missing"),
    ({"returns": np.arange(3, dtype=np.float32)}, "field returns: 3 entries, not 4"),
    ({"xy": np.zeros((1, 4, 3), np.float32)}, "field xy: shape (1, 4, 3), expected [panels, n >= 2, 2]"),
    ({"xy": np.full((1, 4, 2), np.nan, np.float32)}, "field returns or xy: not finite numbers"),
    ({"panels": []}, "field meta.panels: a list of 1 panels"),
    ({"panels": [{"name": "raw state"}]}, "field meta.panels[0]: name, dims, locality, locality_tsne"),
]  # fmt: skip


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("content", "expected"), BAD_TSNE_RECORDS, ids=range(len(BAD_TSNE_RECORDS)))
def test_a_bad_tsne_record_is_one_line_for_mcrs_report(
    content: dict[str, Any] | bytes, expected: str, tmp_path: Path
) -> None:
    path = tmp_path / "fig9" / "map10" / "tsne.npz"
    if isinstance(content, bytes):
        path.parent.mkdir(parents=True)
        path.write_bytes(content)
    else:
        _tsne_record(path, **content)
    with pytest.raises(SystemExit) as info:
        report_main([str(tmp_path / "fig9"), "--out", str(tmp_path / "out")])
    message = str(info.value.code)
    assert message.startswith("mcrs-report: error: ") and "\n" not in message, message
    assert expected in message, message
    assert not (tmp_path / "out").exists()


#: (command line, the error's text): values that used to be accepted or to crash.
BAD_CAMPAIGN_ARGS: list[tuple[list[str], str]] = [
    (["run", "--hours", "nan"], "--hours=nan: must be > 0"),
    (["run", "--hours", "inf"], "--hours=inf: must be > 0"),
    (["run", "--hours", "-1"], "--hours=-1.0: must be > 0"),
    (["run", "--hours", "0"], "--hours=0.0: must be > 0"),
    (["run", "--hours", "1e9"], "--hours=1000000000.0: must be > 0 and <= 8784"),
    (["run", "--hours", "1", "--jobs", "100000000"], "--jobs=100000000: must be >= 1 and <="),
    (["run", "--hours", "1", "--jobs", "-3"], "--jobs=-3: must be >= 1"),
    (["run", "--hours", "1", "--jobs", "0"], "--jobs=0: must be >= 1"),
    (["status", "--only", "../.."], "--only=../..: unknown ../.."),
    (["evaluate", "--evaluation", "../../.."], "--evaluation=../../..: allowed values are"),
]


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(
    ("argv", "expected"), BAD_CAMPAIGN_ARGS, ids=[" ".join(a) for a, _ in BAD_CAMPAIGN_ARGS]
)
def test_a_bad_campaign_argument_is_one_line(argv: list[str], expected: str, tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as info:
        campaign_main([*argv, *_campaign_args(tmp_path, POINTS + EVALUATION)])
    message = str(info.value.code)
    assert message.startswith("mcrs-campaign: error: ") and expected in message, message
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------------ records
def training_record(seed: int = 0, reward: float = 1.0) -> dict[str, Any]:
    """A minimal valid training record (the fields the schema checks)."""
    return {
        "format": RECORD_FORMAT,
        "version": RECORD_VERSION,
        "kind": "training",
        "run_dir": f"outputs/run{seed}",
        "status": "finished",
        "total_env_steps": 100,
        "checkpoint_env_steps": 100,
        "logged_env_steps": 100,
        "loop_time_s": 1.5,
        "final_eval": {"env_step": 100, "episode_reward": reward},
        "sessions": [],
        "config": {"env": {"name": "map10"}, "algo": {"name": "qmix"}, "seed": seed},
        "scalars": {"eval/episode_reward": [[0, 0.5], [100, reward]]},
    }


def evaluation_record() -> dict[str, Any]:
    row = {"policy": "greedy", "env": "map10", "comm_range": 5.0, "seed": 0, "episodes": 4,
           "means": {"episode_reward": 3.0}, "label": None}  # fmt: skip
    return {
        "format": RECORD_FORMAT,
        "version": RECORD_VERSION,
        "kind": "evaluation",
        "run_dir": "outputs/eval",
        "study": "eval",
        "policy": "greedy",
        "config": {"policy": "greedy"},
        "rows": [row],
    }


def _set(record: dict[str, Any], dotted: str, value: Any) -> dict[str, Any]:
    """A copy of ``record`` with ``dotted`` (``rows.0.seed``) set, or deleted when ``value`` is DELETE."""
    out = copy.deepcopy(record)
    *parents, last = dotted.split(".")
    node: Any = out
    for part in parents:
        node = node[int(part)] if isinstance(node, list) else node[part]
    key: Any = int(last) if isinstance(node, list) else last
    if value is DELETE:
        del node[key]
    else:
        node[key] = value
    return out


DELETE = object()
T, E = training_record(), evaluation_record()
#: (record, the field the error names). Each a bad input.
BAD_RECORDS: list[tuple[dict[str, Any], str]] = [
    (_set(T, "kind", "trainin"), "field kind: 'trainin' is not one of training, evaluation"),
    (_set(T, "kind", DELETE), "field kind: missing"),
    (_set(T, "run_dir", DELETE), "field run_dir: missing"),
    (_set(T, "run_dir", 3), "field run_dir: 3 is not a non-empty string"),
    (_set(T, "config", DELETE), "field config: missing"),
    (_set(T, "config", [1, 2]), "field config: [1, 2] is not a mapping"),
    (_set(T, "config.env", "map10"), "field config.env: 'map10' is not a mapping"),
    (_set(T, "config.env.name", DELETE), "field config.env.name: missing"),
    (_set(T, "config.env.name", "../../x"), "field config.env.name: '../../x' is not a plain name"),
    (_set(T, "config.env.name", ".."), "field config.env.name: '..' is not a plain name"),
    (_set(T, "config.env.name", ["map10"]), "field config.env.name: ['map10'] is not a plain name"),
    (_set(T, "config.algo.name", "a/b"), "field config.algo.name: 'a/b' is not a plain name"),
    (_set(T, "config.algo", DELETE), "field config.algo: missing"),
    (_set(T, "config.seed", -1), "field config.seed: -1 is not a whole number >= 0"),
    (_set(T, "config.seed", 1.5), "field config.seed: 1.5 is not a whole number"),
    (_set(T, "config.seed", True), "field config.seed: True is not a whole number"),
    (_set(T, "config.seed", "0"), "field config.seed: '0' is not a whole number"),
    (_set(T, "config.seed", DELETE), "field config.seed: missing"),
    (_set(T, "config.experiment", "../.."), "field config.experiment: '../..' is not a plain name"),
    (_set(T, "config.budget", "/tmp"), "field config.budget: '/tmp' is not a plain name"),
    (_set(T, "status", "done"), "field status: 'done' is not one of finished, stopped"),
    (_set(T, "status", DELETE), "field status: missing"),
    (_set(T, "total_env_steps", -5), "field total_env_steps: -5 is not a whole number >= 0"),
    (_set(T, "total_env_steps", "100"), "field total_env_steps: '100' is not a whole number"),
    (_set(T, "checkpoint_env_steps", 1.5), "field checkpoint_env_steps: 1.5 is not a whole number"),
    (_set(T, "logged_env_steps", -1), "field logged_env_steps: -1 is not a whole number"),
    (_set(T, "loop_time_s", -1.0), "field loop_time_s: -1.0 is negative"),
    (_set(T, "loop_time_s", "fast"), "field loop_time_s: 'fast' is not a finite number"),
    (_set(T, "final_eval", [1]), "field final_eval: [1] is not a mapping"),
    (_set(T, "final_eval.episode_reward", "high"), "field final_eval.episode_reward: 'high' is not a finite"),
    (_set(T, "final_eval.env_step", -100), "field final_eval.env_step: -100 is not a whole number"),
    (_set(T, "sessions", {"a": 1}), "field sessions: not a list of mappings"),
    (_set(T, "sessions", [1, 2]), "field sessions: not a list of mappings"),
    (_set(T, "scalars", DELETE), "field scalars: missing"),
    (_set(T, "scalars", [[0, 1]]), "field scalars: [[0, 1]] is not a mapping"),
    (_set(T, "scalars.eval/episode_reward", {"0": 1}), "field scalars.eval/episode_reward: {'0': 1} is not a list"),
    (_set(T, "scalars.eval/episode_reward.0", [0, 1, 2]), "scalars.eval/episode_reward[0]: [0, 1, 2] is not a [step, value] row"),
    (_set(T, "scalars.eval/episode_reward.0", 5), "scalars.eval/episode_reward[0]: 5 is not a [step, value] row"),
    (_set(T, "scalars.eval/episode_reward.0", [-1, 1.0]), "scalars.eval/episode_reward[0] step: -1 is not a whole"),
    (_set(T, "scalars.eval/episode_reward.1", [100, "x"]), "scalars.eval/episode_reward[1] value: 'x' is not a finite"),
    (_set(T, "scalars.eval/episode_reward.1", [100, None]), "scalars.eval/episode_reward[1] value: None is not a finite"),
    (_set(E, "study", "../../.."), "field study: '../../..' is not a plain name"),
    (_set(E, "study", DELETE), "field study: missing"),
    (_set(E, "policy", ""), "field policy: '' is not a non-empty string"),
    (_set(E, "config", "x"), "field config: 'x' is not a mapping"),
    (_set(E, "rows", []), "field rows: [] is not a non-empty list of rows"),
    (_set(E, "rows", {"a": 1}), "field rows: {'a': 1} is not a non-empty list"),
    (_set(E, "rows.0", "row"), "field rows[0]: 'row' is not a mapping"),
    (_set(E, "rows.0.policy", DELETE), "field rows[0].policy: missing"),
    (_set(E, "rows.0.env", "../map10"), "field rows[0].env: '../map10' is not a plain name"),
    (_set(E, "rows.0.comm_range", -1), "field rows[0].comm_range: -1 is not a distance >= 0"),
    (_set(E, "rows.0.comm_range", "5"), "field rows[0].comm_range: '5' is not a distance >= 0"),
    (_set(E, "rows.0.seed", -1), "field rows[0].seed: -1 is not a whole number >= 0"),
    (_set(E, "rows.0.seed", [0]), "field rows[0].seed: [0] is not a whole number"),
    (_set(E, "rows.0.episodes", 0), "field rows[0].episodes: 0 is not a whole number >= 1"),
    (_set(E, "rows.0.means", [3.0]), "field rows[0].means: [3.0] is not a mapping"),
    (_set(E, "rows.0.means.episode_reward", "3"), "field rows[0].means.episode_reward: '3' is not a finite"),
    (_set(E, "rows.0.means.episode_reward", None), "field rows[0].means.episode_reward: None is not a finite"),
    (_set(E, "rows.0.label", 7), "field rows[0].label: 7 is not a string or null"),
    (_set(E, "rows.0.run", ["a"]), "field rows[0].run: ['a'] is not a string or null"),
]  # fmt: skip

#: (the file's text, the error's text): files carrying the record marker that are not records.
BAD_RECORD_TEXTS: list[tuple[str, str]] = [
    (json.dumps(training_record()).replace('"episode_reward": 1.0', '"episode_reward": NaN'), "NaN is not a number JSON allows"),
    (json.dumps(training_record()).replace('"episode_reward": 1.0', '"episode_reward": Infinity'), "Infinity is not a number JSON allows"),
    (json.dumps(training_record()).replace('[100, 1.0]', '[100, -Infinity]'), "-Infinity is not a number JSON allows"),
    (json.dumps(training_record())[:-20], "not a readable record"),
    ('{"format": "mcrs-record", "version": 1, "kind": "training", "x": ' + "[" * 100_000 + "]" * 100_000 + "}", "nested deeper than"),
    ('{"format": "mcrs-record", "version": 1, "x": ' + "[" * 40 + "]" * 40 + "}", "nested deeper than 32 levels"),
    ('{"format": "mcrs-record", "version": 1, "kind": "training"}\n' + " " * (16 << 20), "larger than 16,777,216 bytes"),
    ('{"format": "mcrs-record", "version": 1, "kind": !!python/object:os.system}', "not a readable record"),
    ('{"format": "mcrs-record", "version": 1}' + "\xff", "not a readable record"),
]  # fmt: skip


def _write_json(path: Path, record: dict[str, Any] | str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(record if isinstance(record, str) else json.dumps(record))
    return path


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("record", "expected"), BAD_RECORDS, ids=[e.split(":")[0] for _, e in BAD_RECORDS])
def test_a_bad_record_field_is_refused_naming_the_file_and_field(
    record: dict[str, Any], expected: str, tmp_path: Path
) -> None:
    path = _write_json(tmp_path / "records" / "x.json", record)
    with pytest.raises(RecordError) as info:
        read_record(path)
    assert str(info.value).startswith(f"{path}: ") and expected in str(info.value), str(info.value)
    with pytest.raises(SystemExit) as exit_info:  # mcrs-report: the same line, nothing reported
        report_main([str(tmp_path / "records"), "--out", str(tmp_path / "report")])
    assert str(exit_info.value.code) == f"mcrs-report: error: {info.value}"
    assert not (tmp_path / "report").exists()


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("text", "expected"), BAD_RECORD_TEXTS, ids=range(len(BAD_RECORD_TEXTS)))
def test_a_bad_record_file_is_refused_in_one_line(text: str, expected: str, tmp_path: Path) -> None:
    path = _write_json(tmp_path / "x.json", text)
    with pytest.raises(RecordError, match=re.escape(expected)) as info:
        read_record(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_the_valid_records_pass() -> None:
    """Guards the cases above: the records they change are valid."""
    assert validate_ok(training_record()) and validate_ok(evaluation_record())


def validate_ok(record: dict[str, Any]) -> bool:
    from mcrs_lab.analysis.record_schema import check_record

    check_record(record)
    return True


# --------------------------------------------------------------------------- logs and record paths
BAD_LOGS: list[tuple[str, str, str]] = [
    ("logs/scalars/eval/episode_reward.csv", "0,1.0\nabc,2.0\n", "episode_reward.csv:2: not a step,value row"),
    ("logs/scalars/eval/episode_reward.csv", "0,1.0\n40,x\n", "episode_reward.csv:2: not a step,value row"),
    ("logs/scalars/eval/episode_reward.csv", "-40,1.0\n", "episode_reward.csv:1: step '-40' is not a whole"),
    ("logs/scalars/eval/episode_reward.csv", "nan,1.0\n", "episode_reward.csv:1: step 'nan' is not a whole"),
    ("logs/scalars/eval/episode_reward.csv", "inf,1.0\n", "episode_reward.csv:1: step 'inf' is not a whole"),
    ("campaign.jsonl", '{"wall_s": 1}\n{not json\n', "campaign.jsonl:2: not a JSON line"),
    ("campaign.jsonl", "[1, 2]\n", "campaign.jsonl:1: not a session"),
    ("campaign.jsonl", "[" * 100_000 + "]" * 100_000 + "\n", "campaign.jsonl:1: not a JSON line"),
]  # fmt: skip


def _run_dir(root: Path, config: str = "env: {name: map10}\nalgo: {name: qmix}\nseed: 0\n") -> Path:
    """A run directory with a config.yaml and one CSV log (no checkpoint: enough for a record)."""
    run = root / "run"
    (run / "logs" / "scalars" / "eval").mkdir(parents=True)
    (run / "config.yaml").write_text(config + "train: {total_env_steps: 40}\n")
    (run / "logs" / "scalars" / "eval" / "episode_reward.csv").write_text("0,1.0\n40,2.0\n")
    return run


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("name", "text", "expected"), BAD_LOGS, ids=range(len(BAD_LOGS)))
def test_a_bad_log_is_refused_naming_the_file_and_line(
    name: str, text: str, expected: str, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    run = _run_dir(tmp_path)
    (run / name).write_text(text)
    with pytest.raises(RecordError, match=re.escape(expected)):
        make_record(run, tmp_path / "records")
    assert campaign_main(["record", str(run), "--records", str(tmp_path / "records")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mcrs-campaign: error: ") and err.count("\n") == 1 and expected in err, err
    assert not (tmp_path / "records").exists()


BAD_METRICS: list[tuple[str, str]] = [
    ("greedy,map10,5,0,4,abc", "line 2: could not convert string to float: 'abc'"),
    ("greedy,map10,5,-1,4,3.0", "line 2: field line 2: seed: -1 is not a whole number"),
    ("greedy,map10,-5,0,4,3.0", "line 2: field line 2: comm_range: -5.0 is not a distance"),
    ("greedy,map10,5,0,0,3.0", "line 2: field line 2: episodes: 0 is not a whole number >= 1"),
    ("greedy,map10,5,0,4,nan", "line 2: field line 2: means.episode_reward: nan is not a finite"),
    ("greedy,../x,5,0,4,3.0", "line 2: field line 2: env: '../x' is not a plain name"),
    ("greedy,map10,5,0.5,4,3.0", "line 2: invalid literal for int()"),
]


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("row", "expected"), BAD_METRICS, ids=[r for r, _ in BAD_METRICS])
def test_a_bad_metrics_csv_is_refused_by_mcrs_report(row: str, expected: str, tmp_path: Path) -> None:
    result = tmp_path / "eval"
    result.mkdir()
    (result / "metrics.csv").write_text(f"policy,env,comm_range,seed,episodes,episode_reward_mean\n{row}\n")
    with pytest.raises(SystemExit) as info:
        report_main([str(result), "--out", str(tmp_path / "report")])
    message = str(info.value.code)
    assert message.startswith(f"mcrs-report: error: {result / 'metrics.csv'}: ") and expected in message, (
        message
    )


#: (a run's config.yaml, the error's text): fields that would put a record outside --records.
BAD_RECORD_PATHS: list[tuple[str, str]] = [
    ("env: {name: map10}\nalgo: {name: qmix}\nseed: 0\nexperiment: ../../../x\n", "experiment='../../../x'"),
    ("env: {name: map10}\nalgo: {name: qmix}\nseed: 0\nbudget: /tmp\n", "budget='/tmp'"),
    ("env: {name: map10}\nalgo: {name: qmix}\nseed: 0\nexperiment: ..\n", "experiment='..'"),
    ("env: {name: ../../x}\nalgo: {name: qmix}\nseed: 0\n", "env.name='../../x'"),
    ("env: {name: map10}\nalgo: {name: ../../x}\nseed: 0\n", "algo.name='../../x'"),
    ("env: {name: map10}\nalgo: {name: qmix}\nseed: -3\n", "seed=-3 (the run's config.yaml): not a whole"),
    ("env: {name: map10}\nalgo: {name: qmix}\nseed: x\n", "seed='x' (the run's config.yaml)"),
]


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("config", "expected"), BAD_RECORD_PATHS, ids=[e for _, e in BAD_RECORD_PATHS])
def test_a_record_is_never_written_outside_records(config: str, expected: str, tmp_path: Path) -> None:
    run = _run_dir(tmp_path / "in", config)
    records = tmp_path / "in" / "records"
    before = sorted(p for p in tmp_path.rglob("*"))
    with pytest.raises(RecordError, match=re.escape(expected)):
        make_record(run, records)
    assert campaign_main(["record", str(run), "--records", str(records)]) == 1
    assert sorted(p for p in tmp_path.rglob("*")) == before  # nothing written anywhere


def test_the_record_path_of_a_good_config_is_under_records(tmp_path: Path) -> None:
    config = {"env": {"name": "map10"}, "algo": {"name": "qmix"}, "seed": 0, "experiment": "baselines"}
    assert training_record_path(tmp_path, config) == tmp_path / "baselines" / "none" / "map10_qmix_seed0.json"


# ------------------------------------------------------------------------------- run config.yaml
BAD_RUN_CONFIGS: list[tuple[str, str]] = [
    (ALIAS_BOMB, "holds YAML anchors or aliases"),
    ("seed: &s 0\nx: *s\n", "holds YAML anchors or aliases"),
    ("a: &a {b: 1}\nc: {<<: *a}\n", "holds YAML anchors or aliases"),
    (DEEP, "is nested deeper than 32 levels"),
    ("seed: 0\n" + "#" * (MAX_YAML_BYTES + 1), "is larger than 1,048,576 bytes"),
    ("seed: 0\nx: ${seed}\n", "holds an interpolation"),
    ("a0: [1, 1]\na1: ['${a0}', '${a0}']\na2: ['${a1}', '${a1}']\n", "holds an interpolation"),
    ("seed: !!python/object/apply:os.system ['true']\n", "is not plain YAML data"),
    ("seed: [1, 2\n", "is not a valid config"),
    ("- 1\n- 2\n", "expected a mapping of fields"),
]  # fmt: skip


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("text", "expected"), BAD_RUN_CONFIGS, ids=range(len(BAD_RUN_CONFIGS)))
def test_a_bad_run_config_is_refused_before_it_is_parsed(text: str, expected: str, tmp_path: Path) -> None:
    path = tmp_path / "config.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=re.escape(expected)) as info:
        _read_run_config(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)
    run = _run_dir(tmp_path / "r")  # mcrs-report and mcrs-campaign record: skipped, with the reason
    (run / "config.yaml").write_text(text)
    skipped = find_runs([run]).skipped
    assert not text.startswith("- ") or not find_runs([run]).training
    assert text.startswith("- ") or any(expected in s.reason for s in skipped), skipped


# ---------------------------------------------------------------------------------- checkpoints
def _zip_bomb(path: Path, inflated: int = 64 << 20) -> None:
    """A torch-like archive whose tensor member is deflated zeros: ``inflated`` bytes from a few hundred kB."""
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("archive/data.pkl", b"\x80\x02}q\x00.", compress_type=zipfile.ZIP_STORED)
        info = zipfile.ZipInfo("archive/data/0")
        info.compress_type = zipfile.ZIP_DEFLATED
        with archive.open(info, "w", force_zip64=True) as member:
            chunk = bytes(1 << 20)
            for _ in range(inflated >> 20):
                member.write(chunk)


def _zip_deflated_member(path: Path) -> None:
    torch.save({"a": torch.zeros(4)}, path)
    data = {m.filename: zipfile.ZipFile(path).read(m) for m in zipfile.ZipFile(path).infolist()}
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, content in data.items():
            archive.writestr(name, content)


def _zip_two_folders(path: Path) -> None:
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("a/data.pkl", b".")
        archive.writestr("b/data.pkl", b".")


def _zip_dotdot(path: Path) -> None:
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("a/../../etc/data.pkl", b".")


def _zip_absolute(path: Path) -> None:
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr(zipfile.ZipInfo("/a/data.pkl"), b".")


def _zip_truncated(path: Path) -> None:
    torch.save({"format": ckpt.FORMAT, "version": ckpt.VERSION, "a": torch.zeros(1000)}, path)
    path.write_bytes(path.read_bytes()[:2000])


def _zip_empty_archive(path: Path) -> None:
    with zipfile.ZipFile(path, "w"):
        pass
    path.write_bytes(b"PK\x03\x04" + path.read_bytes())


def _legacy_pickle(path: Path) -> None:
    torch.save({"format": ckpt.FORMAT, "version": ckpt.VERSION}, path, _use_new_zipfile_serialization=False)


def _directory(path: Path) -> None:
    path.mkdir()


BAD_CHECKPOINT_FILES: list[tuple[Callable[[Path], None], str]] = [
    (_zip_bomb, "is compressed (torch stores members uncompressed; a zip bomb?)"),
    (_zip_deflated_member, "is compressed"),
    (_zip_two_folders, "its archive members are in 2 folders"),
    (_zip_dotdot, "has an archive member outside its folder"),
    (_zip_absolute, "has an archive member outside its folder"),
    (_zip_truncated, "it is truncated or corrupt"),
    (_zip_empty_archive, "it has 0 archive members"),
    (_legacy_pickle, "not a zip archive"),
    (_directory, "does not exist"),
]


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(
    ("writer", "expected"), BAD_CHECKPOINT_FILES, ids=[w.__name__ for w, _ in BAD_CHECKPOINT_FILES]
)
def test_a_bad_checkpoint_is_refused_before_torch_load(
    writer: Callable[[Path], None], expected: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "model.pt"
    writer(path)
    monkeypatch.setattr(torch, "load", _never)  # refused from the archive's directory alone
    with pytest.raises(ckpt.CheckpointError, match=re.escape(expected)) as info:
        ckpt.load(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def _never(*args: Any, **kwargs: Any) -> None:
    raise AssertionError("torch.load was reached")


@pytest.fixture(scope="module")
def agent_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    """A policy checkpoint as mcrs-train writes its ``model_*.pt`` (a tiny untrained agent)."""
    from omegaconf import OmegaConf

    from mcrs.env.config import from_mapping
    from mcrs.env.core import N_ACTIONS
    from mcrs.models.agent import RecurrentAgent

    config = OmegaConf.to_container(compose_config("env=map10"), resolve=True, enum_to_str=True)
    env = from_mapping(config["env"])
    model = config["model"]
    agent = RecurrentAgent(env.obs_dim, N_ACTIONS, env.n_uavs, model["hidden_dim"], model["agent_id"],
                           model["last_action"])  # fmt: skip
    state = {"config": config, "learner": {"agent": agent.state_dict()}}
    path = tmp_path_factory.mktemp("agent") / "model_000000040.pt"
    ckpt.save_atomic(state, path)
    return path, state


def _nan_weight(state: dict[str, Any]) -> None:
    name = next(iter(state["learner"]["agent"]))
    state["learner"]["agent"][name][0] = float("nan")


def _inf_weight(state: dict[str, Any]) -> None:
    name = list(state["learner"]["agent"])[-1]
    state["learner"]["agent"][name].fill_(float("inf"))


def _wrong_shape(state: dict[str, Any]) -> None:
    name = next(iter(state["learner"]["agent"]))
    state["learner"]["agent"][name] = torch.zeros(3, 3)


def _no_config(state: dict[str, Any]) -> None:
    del state["config"]


def _no_model(state: dict[str, Any]) -> None:
    del state["config"]["model"]


def _no_agent(state: dict[str, Any]) -> None:
    del state["learner"]["agent"]


def _string_weight(state: dict[str, Any]) -> None:
    name = next(iter(state["learner"]["agent"]))
    state["learner"]["agent"][name] = "weights"


def _bad_env(state: dict[str, Any]) -> None:
    state["config"]["env"]["width"] = -3


def _huge_env_value(state: dict[str, Any]) -> None:
    state["config"]["env"]["comm_range"] = 10**400  # float() overflows: not a ValueError


BAD_POLICIES: list[tuple[Callable[[dict[str, Any]], None], str]] = [
    (_nan_weight, "hold NaN or inf"),
    (_inf_weight, "hold NaN or inf"),
    (_wrong_shape, "its agent cannot be built: Error(s) in loading state_dict"),
    (_no_config, "lacks a usable config or agent (KeyError"),
    (_no_model, "lacks a usable config or agent (KeyError"),
    (_no_agent, "lacks a usable config or agent (KeyError"),
    (_string_weight, "or are not tensors"),
    (_bad_env, "lacks a usable config or agent (ValueError"),
    (_huge_env_value, "lacks a usable config or agent (OverflowError"),
]


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("change", "expected"), BAD_POLICIES, ids=[c.__name__ for c, _ in BAD_POLICIES])
def test_mcrs_eval_refuses_a_bad_policy_checkpoint(
    change: Callable[[dict[str, Any]], None], expected: str, agent_checkpoint, tmp_path: Path
) -> None:
    from mcrs.env.config import scenario
    from mcrs.policies.trained import TrainedPolicy

    _, state = agent_checkpoint
    state = copy.deepcopy(state)
    change(state)
    path = ckpt.save_atomic(state, tmp_path / "model.pt")
    with pytest.raises(ckpt.CheckpointError, match=re.escape(expected)) as info:  # mcrs-eval: one line
        TrainedPolicy.from_checkpoint(path, scenario("map10"))
    assert "\n" not in str(info.value)


def test_the_good_policy_checkpoint_loads(agent_checkpoint) -> None:
    from mcrs.env.config import scenario
    from mcrs.policies.trained import TrainedPolicy

    TrainedPolicy.from_checkpoint(agent_checkpoint[0], scenario("map10"))


# ------------------------------------------------------------------------------ mcrs-results blocks
BAD_BLOCKS: list[tuple[str, str]] = [
    ("<!-- table final.md of: mcrs-report results/records --marl-eval /tmp/x.json -->\n|a|\n<!-- end table -->\n", "--marl-eval writes a file"),
    ("<!-- table final.md of: mcrs-report results/records --marl-eval=/tmp/x.json -->\n|a|\n<!-- end table -->\n", "--marl-eval writes a file"),
    ("<!-- table final.md of: mcrs-report results/records --marl /tmp/x.json -->\n|a|\n<!-- end table -->\n", "--marl writes a file"),
    ("<!-- table final.md of: mcrs-report results/records --ou /tmp/x -->\n|a|\n<!-- end table -->\n", "--ou writes a file"),
    ("<!-- table final.md of: mcrs-report results/records --out /tmp/x -->\n|a|\n<!-- end table -->\n", "leave --out out"),
    ("<!-- figure curves.png of: mcrs-report results/records -->\n![a](../../../x.png)\n<!-- end figure -->\n", "outside"),
    ("<!-- figure curves.png of: mcrs-report results/records -->\n![a](/tmp/x.png)\n<!-- end figure -->\n", "outside"),
]  # fmt: skip


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("text", "expected"), BAD_BLOCKS, ids=range(len(BAD_BLOCKS)))
def test_a_document_block_cannot_make_mcrs_results_write_elsewhere(
    text: str, expected: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mcrs_lab.analysis.doc_tables as doc_tables

    repo = tmp_path / "repo"
    (repo / "docs").mkdir(parents=True)
    doc = repo / "docs" / "R.md"
    doc.write_text(text)
    monkeypatch.setattr(doc_tables, "generate", lambda blocks, root: dict.fromkeys(blocks, b"png"))
    for action in ("check", "update"):
        try:
            results_main([action, str(doc)])
        except SystemExit as error:
            message = str(error.code)
            assert message.startswith(f"mcrs-results: error: {doc}: ") and expected in message, message
        else:
            pytest.fail(f"mcrs-results {action} accepted the block")
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == [
        "repo",
        "repo/docs",
        "repo/docs/R.md",
    ]


# ------------------------------------------------------------------------------ mcrs-report outputs
DEEP = "map10: " + "[" * 40 + "]" * 40 + "\n"
DEEPER = "map10: " + "[" * 100_000 + "\n"  # the stack of a recursive loader, not the size limit
#: (how the case's files are made, the command line's tail, the error's text): mcrs-report's own files and
#: arguments; every case's files are left as they were, and nothing else is written.
BAD_REPORT_ARGS: list[tuple[dict[str, bytes | None], list[str], str]] = [
    ({"a_file": b"mine"}, ["--out", "{a_file}"], "--out {a_file}: a file, not a folder"),
    ({"config.yaml": b"seed: 0\n"}, ["--out", "{out}", "--marl-eval", "{config}"], "the file exists; pass --force"),
    ({"folder": None}, ["--out", "{out}", "--marl-eval", "{folder}"], "--marl-eval {folder}: a folder: name the JSON file"),
    ({}, ["--out", "{out}", "--marl-eval", "{tmp}/new.json", "--env", "map99"], "no readable runs of map map99"),
    ({"claims.bin": bytes(range(256))}, ["--out", "{out}", "--claims", "{claims}"], "not UTF-8"),
    ({"deep.yaml": DEEP.encode()}, ["--out", "{out}", "--claims", "{deep}"], "nested deeper than"),
    ({"deeper.yaml": DEEPER.encode()}, ["--out", "{out}", "--claims", "{deeper}"], "is not a valid config (bad YAML"),
    ({"alias.yaml": b"a: &x [1]\nmap20: *x\n"}, ["--out", "{out}", "--claims", "{alias}"], "anchors or aliases"),
    ({"a_file": b"mine"}, ["--out", "{a_file}/report"], "Not a directory"),
    ({}, ["--out", "{out}", "--seed", "-5"], "--seed=-5: must be in [0, 2**32 - 1]"),
]  # fmt: skip


@pytest.mark.bad_tool_input
@pytest.mark.parametrize(("files", "tail", "expected"), BAD_REPORT_ARGS, ids=range(len(BAD_REPORT_ARGS)))
def test_a_bad_report_output_or_claims_file_is_one_line_and_replaces_nothing(
    files: dict[str, bytes | None], tail: list[str], expected: str, tmp_path: Path
) -> None:
    names = {"tmp": str(tmp_path), "out": str(tmp_path / "out")}
    for name, content in files.items():
        names[name.split(".")[0]] = str(tmp_path / name)
        if content is None:
            (tmp_path / name).mkdir()
        else:
            (tmp_path / name).write_bytes(content)
    records = str(Path(__file__).resolve().parents[1] / "results" / "records" / "heuristics" / "map20")
    with pytest.raises(SystemExit) as info:
        report_main([records, *(t.format(**names) for t in tail)])
    message = str(info.value.code)
    assert message.startswith("mcrs-report: error: ") and "\n" not in message, message
    assert expected.format(**names) in message, message
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(files)  # no --out, no marl-eval file
    for name, content in files.items():
        if content is not None:
            assert (tmp_path / name).read_bytes() == content


def test_a_campaign_file_that_is_a_folder_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(
        SystemExit, match=r"^mcrs-campaign: error: --matrix=.*: a folder: name the campaign file"
    ):
        campaign_main(["status", "--matrix", str(tmp_path)])


def test_campaign_record_into_a_file_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``--records`` naming a file: each run is refused in one line (exit 1), the file is left as it was."""
    from tests.test_report import make_evaluation

    records = tmp_path / "records"
    records.write_text("mine")
    evaluation = make_evaluation(tmp_path, "greedy_0", "greedy", 5.0, 0, found=3)
    assert campaign_main(["record", str(evaluation), "--records", str(records)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mcrs-campaign: error: cannot write the record of ") and err.count("\n") == 1, err
    assert "Not a directory" in err and records.read_text() == "mine"


# -------------------------------------------------------------------------------------- env.name
BAD_LABELS = ["env.name=..", "env.name=.", "env.name=../x", "env.name=.hidden", "algo.name=..",
              "algo.name=.", "env.name=a\\b", "experiment=..", "budget=.."]  # fmt: skip


@pytest.mark.bad_tool_input
@pytest.mark.parametrize("override", BAD_LABELS)
def test_a_label_that_would_leave_outputs_is_refused(override: str) -> None:
    from omegaconf import OmegaConf

    cfg = compose_config()
    key, value = override.split("=", 1)
    OmegaConf.update(cfg, key, value, merge=False)
    with pytest.raises(ConfigError, match=re.escape(f"{key}={value!r}: must be a non-empty label")):
        validate(cfg)


# -------------------------------------------------------------------------- the five reproductions
def _measured(action: Callable[[], object]) -> tuple[BaseException, float, float]:
    """The exception ``action`` raises, its wall time (s) and the peak of Python's allocations (MB)."""
    tracemalloc.start()
    start = time.perf_counter()
    try:
        action()
    except (SystemExit, Exception) as error:
        caught: BaseException = error
    else:
        raise AssertionError("accepted")
    finally:
        seconds = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1] / 1e6
        tracemalloc.stop()
    return caught, seconds, peak


def test_the_campaign_evaluation_named_dot_dot_is_refused_and_removes_nothing(tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    (victim / "sub").mkdir(parents=True)
    (victim / "sub" / "keep.txt").write_text("mine")
    outputs = tmp_path / "a" / "outputs"
    args = _campaign_args(tmp_path, POINTS + EVALUATION.replace("shield:", "'../../..':"))
    args[args.index("--outputs") + 1] = str(outputs)
    error, seconds, peak = _measured(lambda: campaign_main(["evaluate", *args]))
    assert "evaluation name='../../..': must be a plain name" in str(error) and "\n" not in str(error)
    assert seconds < 2 and peak < 200, (seconds, peak)
    # Even a job built around the check (a forged name) cannot remove a folder outside the outputs.
    (point,) = [p for p in load_matrix(tmp_path / "m.yaml")[0] if p.settings == (("env.comm_range", 0),)]
    forged = Evaluation("../../../victim", "t", ("figa",), ("greedy",), 1, (0,), (("sub", ()),))
    job = EvaluationJob(forged, "sub", (), "map10", "greedy", "..")
    with pytest.raises(RecordError, match="outside"):
        run_job(job, outputs, tmp_path / "records")
    assert (victim / "sub" / "keep.txt").read_text() == "mine"
    assert point.env == "map10"


def test_the_campaign_leaves_a_live_users_run_alone(tmp_path: Path, capsys) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(POINTS)
    point = load_matrix(matrix)[0][0]
    outputs = tmp_path / "outputs"
    run_dir = point.run_dir(outputs)
    lock = RunLock(run_dir)  # a user's mcrs-train on the point, before its first checkpoint
    (run_dir / "config.yaml").write_text("mine")
    campaign = Campaign([point], outputs, tmp_path / "records", 40)
    start = time.perf_counter()
    assert campaign._launch(Progress(point, "missing", 0), ["false"]) is None
    assert time.perf_counter() - start < 2
    out = capsys.readouterr().out.strip()
    assert out == (
        f"not started: {point.id}: its run directory {run_dir} is in use by process {__import__('os').getpid()}: "
        "the campaign leaves a live run alone; run the campaign again once it has ended"
    )
    assert sorted(p.name for p in run_dir.parent.iterdir()) == [run_dir.name]  # not moved aside
    assert (run_dir / "config.yaml").read_text() == "mine" and not (run_dir / LOG).exists()
    campaign._record(point)  # nor recorded (or pruned) while it runs
    assert "is in use by process" in capsys.readouterr().out and not (tmp_path / "records").exists()
    lock.release()
    # Once it has ended: a directory the campaign did not start is still not moved.
    assert campaign._launch(Progress(point, "missing", 0), ["false"]) is None
    assert "holds a run that mcrs-campaign did not start (no campaign.log)" in capsys.readouterr().out
    assert sorted(p.name for p in run_dir.parent.iterdir()) == [run_dir.name]


def test_a_duplicated_record_counts_once_and_a_contradictory_one_is_refused(tmp_path: Path, capsys) -> None:
    records = tmp_path / "records"
    _write_json(records / "a" / "map10_qmix_seed0.json", training_record(0))
    _write_json(records / "b" / "map10_qmix_seed0.json", training_record(0))  # a copy
    _write_json(records / "a" / "map10_qmix_seed1.json", training_record(1))
    runs = find_runs([records])
    assert sorted(r.seed for r in runs.training) == [0, 1]  # two seeds, not three
    assert [s.reason for s in runs.skipped] == [
        f"a copy of {records / 'a' / 'map10_qmix_seed0.json'} (same content hash): counted once"
    ]
    _write_json(records / "c" / "map10_qmix_seed0.json", training_record(0, reward=9.0))
    error, seconds, peak = _measured(lambda: report_main([str(records), "--out", str(tmp_path / "r")]))
    assert str(error) == (
        f"mcrs-report: error: {records / 'c' / 'map10_qmix_seed0.json'} and {records / 'a' / 'map10_qmix_seed0.json'} "
        "record the same point (same config and seed) with different results: keep one of them (a second "
        "record is not another seed)"
    )
    assert seconds < 2 and peak < 200 and not (tmp_path / "r").exists()


def test_an_alias_bomb_config_is_refused_at_once(tmp_path: Path) -> None:
    path = tmp_path / "config.yaml"
    path.write_text(ALIAS_BOMB)
    assert len(ALIAS_BOMB) < 1000
    error, seconds, peak = _measured(lambda: _read_run_config(path))
    assert isinstance(error, ConfigError) and "holds YAML anchors or aliases" in str(error)
    assert seconds < 2 and peak < 200, (seconds, peak)


def _refuse_zip_bomb(path: Path, inflated: int) -> None:
    from mcrs.env.config import scenario
    from mcrs.policies.trained import TrainedPolicy

    _zip_bomb(path, inflated)
    assert path.stat().st_size < inflated / 900  # a few kB per MB inflated
    error, seconds, peak = _measured(lambda: TrainedPolicy.from_checkpoint(path, scenario("map10")))
    assert isinstance(error, ckpt.CheckpointError) and "is compressed" in str(error), error
    assert seconds < 2 and peak < 200, (seconds, peak)


def test_a_zip_bomb_checkpoint_is_refused_at_once(tmp_path: Path) -> None:
    """256 MB inflated (building a bigger bomb costs the test its time: the next test is the issue's)."""
    _refuse_zip_bomb(tmp_path / "model.pt", 256 << 20)


@pytest.mark.slow
def test_the_issues_2_4_gb_zip_bomb_is_refused_at_once(tmp_path: Path) -> None:
    """The issue's bomb: 2.4 GB of zeros in 2.4 MB (slow: about 17 s to compress here)."""
    _refuse_zip_bomb(tmp_path / "model.pt", 2400 << 20)


# --------------------------------------------------------------------------------------- the count
def _cases() -> int:
    marked = [
        t for t in globals().values() if any(m.name == "bad_tool_input" for m in getattr(t, "pytestmark", []))
    ]
    return sum(len(next(m for m in t.pytestmark if m.name == "parametrize").args[1]) for t in marked)


def test_the_documented_tool_count_is_the_suites(capsys: pytest.CaptureFixture) -> None:
    """README.md and docs/RELIABILITY.md state the number of bad tool inputs: exactly the cases marked
    ``bad_tool_input`` (``pytest -m bad_tool_input tests/test_bad_inputs_tools.py`` runs them)."""
    total = _cases()
    with capsys.disabled():
        print(f"\nbad tool inputs tried: {total}")
    assert total >= 100
    root = Path(__file__).resolve().parents[1]
    for doc in ("README.md", "docs/RELIABILITY.md"):
        text = " ".join((root / doc).read_text().split())
        found = {int(n.replace(",", "")) for n in re.findall(r"(\d[\d,]*) bad tool inputs", text)}
        assert found == {total}, f"{doc} states {sorted(found)} bad tool inputs; the suite tries {total}"


# ------------------------------------------------------------------------------ bookkeeping (trains)
@pytest.mark.slow
def test_resuming_a_finished_run_three_times_leaves_one_final_evaluation_row(tmp_path: Path) -> None:
    """The old code evaluated (and logged a row, and saved) again on every resume of a finished run."""
    from mcrs.experiment.training.trainer import Experiment

    run_dir = tmp_path / "run"
    cfg = compose_config("train.total_env_steps=40", "train.eval_interval=40")
    Experiment(cfg, run_dir).run()
    log = run_dir / "logs" / "scalars" / "eval" / "episode_reward.csv"
    rows = log.read_text().splitlines()
    last = ckpt.checkpoint_path(run_dir).read_bytes()
    for _ in range(3):
        result = Experiment(cfg, run_dir, resume=True).run()
        assert result["episode_reward"] == float(rows[-1].split(",")[1])
    assert log.read_text().splitlines() == rows and [r.split(",")[0] for r in rows].count("40") == 1
    assert ckpt.checkpoint_path(run_dir).read_bytes() == last  # nothing saved again


@pytest.mark.slow
def test_a_foreign_replay_block_is_refused_on_resume(tmp_path: Path) -> None:
    """A replay block copied from another run (here: another seed) under this run's block name."""
    import shutil

    from mcrs.experiment.training.trainer import Experiment

    runs = {}
    for seed in (0, 1):
        runs[seed] = tmp_path / f"run{seed}"
        Experiment(compose_config("train.total_env_steps=40", f"seed={seed}"), runs[seed]).run()
    (ours,) = sorted(ckpt.checkpoint_path(runs[0]).parent.glob("replay_*.pt"))
    (theirs,) = sorted(ckpt.checkpoint_path(runs[1]).parent.glob("replay_*.pt"))
    shutil.copyfile(theirs, ours)
    with pytest.raises(ckpt.CheckpointError) as info:
        Experiment(compose_config("train.total_env_steps=80", "seed=0"), runs[0], resume=True)
    assert f"{ours} does not belong to this run: seed: 1 in the checkpoint, 0 in this run" in str(info.value)
