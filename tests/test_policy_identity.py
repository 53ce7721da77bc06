"""How records and reports name a policy: a heuristic by its name, a trained one by its label and its run
(``<experiment>/<run folder>``), read from the run's config.yaml, which is bounded before it is parsed."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

from mcrs.policies import export
from mcrs_lab.analysis.policy_identity import policy_label, trained_run_id


def _run(root: Path, name: str, config: str) -> Path:
    run = root / name
    (run / "checkpoints").mkdir(parents=True)
    (run / "config.yaml").write_text(config)
    return run


def test_a_trained_policy_is_named_by_its_algorithm_and_its_experiments_run(tmp_path: Path) -> None:
    run = _run(
        tmp_path / "shields_view", "map20_qmix_seed0", "experiment: shields_view\nalgo:\n  name: qmix\n"
    )
    for policy in (run, run / "checkpoints" / "model_000800000.pt"):  # a run directory or one checkpoint
        assert policy_label(str(policy)) == "trained qmix"
        assert trained_run_id(str(policy)) == "shields_view/map20_qmix_seed0"
    other = _run(
        tmp_path / "shields_gamma", "map20_qmix_seed0", "experiment: shields_gamma\nalgo:\n  name: qmix\n"
    )
    assert trained_run_id(str(other)) != trained_run_id(str(run))  # one folder name, two experiments


def test_heuristics_and_runs_without_a_usable_config_have_no_run(tmp_path: Path) -> None:
    assert (policy_label("greedy"), trained_run_id("greedy")) == ("greedy", None)
    lost = tmp_path / "gone" / "model_000100000.pt"  # the checkpoint's run is not here
    assert (policy_label(str(lost)), trained_run_id(str(lost))) == ("trained model_000100000", None)
    no_experiment = _run(tmp_path, "plain", "algo:\n  name: vdn\n")
    assert (policy_label(str(no_experiment)), trained_run_id(str(no_experiment))) == ("trained vdn", None)
    # An interpolation in a saved (resolved) config is refused unparsed: the file's name stands in.
    tampered = _run(tmp_path, "tampered", "experiment: ${oc.env:HOME}\nalgo:\n  name: qmix\n")
    assert (policy_label(str(tampered)), trained_run_id(str(tampered))) == ("trained tampered", None)
    listed = _run(tmp_path, "listed", "- not a mapping\n")
    assert (policy_label(str(listed)), trained_run_id(str(listed))) == ("trained listed", None)


def _exported(path: Path, algo: object) -> Path:
    """A ``.pt2`` that holds only the description ``mcrs-export`` writes (all the label reads of it)."""
    description = {"format": export.FORMAT, "version": export.VERSION, "algo": algo}
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr(f"{path.stem}/extra/{export.DESCRIPTION}", json.dumps(description))
    return path


def test_an_exported_agent_is_named_by_the_algorithm_its_description_names(tmp_path: Path) -> None:
    agent = _exported(tmp_path / "q.pt2", "qmix")
    assert (policy_label(str(agent)), trained_run_id(str(agent))) == ("trained qmix", None)
    # A name that is not a plain algorithm name (it becomes part of a record's file name) is not used.
    for algo in ("../../x", "QMIX", 7, "a" * 40):
        assert policy_label(str(_exported(tmp_path / "r.pt2", algo))) == "trained r"
    # A file that is not an export keeps the file's name.
    (tmp_path / "s.pt2").write_text("not a zip")
    assert policy_label(str(tmp_path / "s.pt2")) == "trained s"
