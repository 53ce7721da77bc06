"""Figures 5 and 9 of the paper's campaign from records: the communication-range evaluation of figure 7's
finished policies, and the t-SNE of a run's episodic memory recorded before the run is pruned."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from mcrs.experiment.run import checkpoint as ckpt
from mcrs_lab.analysis import comm_range as cr
from mcrs_lab.analysis import tsne
from mcrs_lab.analysis.evaluation_rows import EvaluationRow
from mcrs_lab.analysis.report import main as report_main
from mcrs_lab.campaign.cli import main as campaign_main
from mcrs_lab.campaign.evaluations import load_evaluations, plan
from mcrs_lab.campaign.figure9 import load_tsne, missing
from mcrs_lab.campaign.matrix import load_matrix, select

PAPER = Path(__file__).resolve().parents[1] / "mcrs_lab" / "campaign" / "section6_paper.yaml"


def test_the_paper_file_evaluates_figure_5_and_keeps_figure_9(tmp_path: Path) -> None:
    points, titles = load_matrix(PAPER)
    fig5 = next(e for e in load_evaluations(PAPER, set(titles)) if e.name == "fig5")
    assert fig5.of == ("fig7",) and fig5.algos == ("qmix", "cnn_semu")
    assert fig5.heuristics == ("random", "lawnmower", "greedy", "coverage")
    # the training's evaluation episodes: 32 of seed 1000000 (conf/budget/campaign.yaml, train.eval_seed)
    assert (fig5.episodes, fig5.seeds) == (32, (1_000_000,))
    assert dict(fig5.variants) == {f"rc{k}": (f"env.comm_range={k}",) for k in range(11)}
    chosen = [p for p in points if fig5.evaluates(p)]
    assert sorted({p.algo for p in chosen}) == ["cnn_semu", "qmix"] and {p.env for p in chosen} == {"map20"}
    jobs, left_out = plan([fig5], chosen, tmp_path)  # nothing recorded here: the heuristics only
    assert {j.policy for j in jobs} == set(fig5.heuristics) and len(left_out) == len(chosen)
    (fig9,) = load_tsne(PAPER, points)
    assert (fig9.name, fig9.env, fig9.seed, fig9.samples) == ("fig9", "map20", 1, 20_000)
    assert fig9.memory.id == "baselines/map20_cnn_semu_seed1"
    assert [p.id for p in fig9.embeddings] == ["baselines/map20_semu_seed1", "baselines/map20_cnn_semu_seed1"]
    assert fig9.memory in select(points, ["fig7"])
    # the runner makes (or, near its deadline, defers) only a t-SNE not recorded yet; the paper's is
    assert missing([fig9], tmp_path) == [fig9]
    assert missing([fig9], PAPER.parents[2] / "results" / "records" / "paper") == []


def _row(policy: str, rc: float, seed: int, found: float, run: str | None = None) -> EvaluationRow:
    label = None if run is None else "trained qmix"
    return EvaluationRow(Path(f"{policy}{rc}{seed}{run}"), policy, "map20", rc, seed, 32, {"targets_found": found},
                         label, run)  # fmt: skip


def test_a_trained_policys_seeds_are_its_training_runs() -> None:
    """Two runs, one evaluated on two seeds: each run counts once, by its mean over its seeds."""
    rows = [
        _row("o/a", 5.0, 0, 10.0, "b/a"),
        _row("o/a", 5.0, 1, 12.0, "b/a"),
        _row("o/b", 5.0, 0, 20.0, "b/b"),
        _row("greedy", 5.0, 0, 3.0),
        _row("greedy", 5.0, 1, 5.0),
    ]
    curves = cr.curves_from_evaluations(rows)
    trained, greedy = curves["trained qmix"], curves["greedy"]
    assert trained.seeds.tolist() == [2] and trained.mean["targets_found"][0] == pytest.approx((11 + 20) / 2)
    assert greedy.seeds.tolist() == [2] and greedy.mean["targets_found"][0] == pytest.approx(4.0)


def test_figure_5s_statement_is_tested_paired_over_the_trained_runs() -> None:
    """At the largest R_c against the smallest, each training run against itself: a gain every run shows
    passes a paired test that Welch's would not (the runs differ more from each other than R_c moves them);
    a run evaluated at one range only is not paired, a heuristic not tested."""
    gains = {"b/a": (10.0, 12.0), "b/b": (20.0, 22.5), "b/c": (30.0, 31.5)}  # (R_c 0, R_c 4) per run
    rows = [
        _row(f"o/{run[-1]}", rc, 0, found, run)
        for run, pair in gains.items()
        for rc, found in zip((0.0, 4.0), pair, strict=True)
    ]
    rows += [_row("o/d", 0.0, 0, 99.0, "b/d"), _row("greedy", 0.0, 0, 1.0), _row("greedy", 4.0, 0, 9.0)]
    for row in rows:
        row.means["uncertainty"] = 50.0 - row.means["targets_found"]  # falls as targets rise
    (targets, uncertainty) = tests = cr.range_tests(rows)
    assert [(label, metric) for label, metric, _ in tests] == [
        ("trained qmix", "targets_found"),
        ("trained qmix", "uncertainty"),
    ]
    found = targets[2]
    high, low = np.array([12.0, 22.5, 31.5]), np.array([10.0, 20.0, 30.0])
    assert found.test == "paired" and found.diff == pytest.approx(2.0)
    assert found.p == pytest.approx(stats.ttest_rel(high, low).pvalue)
    assert stats.ttest_ind(high, low, equal_var=False).pvalue > 0.5  # unpaired, the gain drowns
    assert found.p_holm == pytest.approx(min(1.0, 2 * found.p)) and found.outcome == "holds"
    assert uncertainty[2].diff == pytest.approx(-2.0) and uncertainty[2].outcome == "holds"
    table = cr.range_tests_table(tests)
    assert "| trained qmix | targets found (higher)" in table and "R_c 4 vs R_c 0: Δ +2.00" in table
    assert table.count("paired over seeds") == 2 and table.splitlines()[2].endswith("| yes              |")
    one = cr.range_tests([r for r in rows if r.run in ("b/a", None)])  # one run: no test
    assert [t.outcome for _, _, t in one] == ["few", "few"] and "one seed: no test" in cr.range_tests_table(
        one
    )


def test_figure_9_is_drawn_from_its_record_alone(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    returns = rng.uniform(0, 10, 60).astype(np.float32)
    panels = [
        {"name": n, "dims": 4, "locality": 0.5, "locality_tsne": 0.4} for n in ("raw state", "cnn_semu keys")
    ]
    meta = {"format": tsne.TSNE_FORMAT, "version": tsne.TSNE_VERSION, "env": "map20", "panels": panels,
            "states": {"run": "baselines/map20_cnn_semu_seed1", "algo": "cnn_semu", "memory_size": 1000}}  # fmt: skip
    xy = rng.normal(size=(2, 60, 2)).astype(np.float32)
    path = tsne.write_npz_record(
        tmp_path / "fig9" / "map20" / "tsne.npz", {"xy": xy, "returns": returns}, meta
    )
    arrays, read = tsne.read_npz_record(path, tsne.TSNE_FORMAT)
    assert np.array_equal(arrays["xy"], xy) and read["panels"] == panels
    out = tmp_path / "report"
    assert report_main([str(tmp_path / "fig9"), "--out", str(out)]) == 0
    assert (out / "tsne.png").read_bytes().startswith(b"\x89PNG")
    table = (out / "tsne.md").read_text()
    assert "60 states drawn from the D_E of `baselines/map20_cnn_semu_seed1`" in table
    assert "| cnn_semu keys  |    4 |" in table


FIG9 = """
budget: smoke
seeds: [0]
figures:
  figa:
    experiment: baselines
    env: [map10]
    algo: [semu, cnn_semu]
tsne:
  fig9:
    of: figa
    env: map10
    seed: 0
    memory: cnn_semu
    embeddings: [semu, cnn_semu]
    samples: 50
"""


@pytest.mark.slow
def test_the_runner_records_the_states_before_pruning_and_the_tsne_once_both_runs_end(
    tmp_path: Path, capsys
) -> None:
    matrix = tmp_path / "m.yaml"
    matrix.write_text(FIG9)
    outputs, records = tmp_path / "outputs", tmp_path / "records"
    args = ["--matrix", str(matrix), "--outputs", str(outputs), "--records", str(records)]
    semu, cnn_semu = load_matrix(matrix)[0]
    # the memory run first: its states are recorded, then it is pruned; the t-SNE waits for SEMU
    assert campaign_main(["run", *args, "--hours", "2", "--jobs", "1", "--only", cnn_semu.id]) == 0
    out = capsys.readouterr().out
    states = records / "fig9" / "map10" / "states.npz"
    assert "tsne fig9: 50 of " in out and out.index(str(states)) < out.index("pruned ")
    assert f"tsne fig9: waits for {semu.id}" in out and not (records / "fig9" / "map10" / "tsne.npz").exists()
    payload = ckpt.load(ckpt.checkpoint_path(cnn_semu.run_dir(outputs)), mmap=True)
    assert "callbacks.memory.memory" in payload["pruned"]["dropped"]
    assert "memory" not in payload["callbacks"]["memory"] and "embedding" in payload["callbacks"]["memory"]
    arrays, meta = tsne.read_npz_record(states, tsne.STATES_FORMAT)
    assert len(arrays["returns"]) == 50 and meta["run"] == cnn_semu.id and arrays["codes"].dtype == np.uint8
    assert campaign_main(["status", *args]) == 0
    assert (
        f"tsne fig9: states recorded, the t-SNE waits for {semu.id}, {cnn_semu.id}" in capsys.readouterr().out
    )
    # SEMU ends: the t-SNE from the recorded states and both (pruned) runs' embeddings
    assert campaign_main(["run", *args, "--hours", "2", "--jobs", "1"]) == 0
    out = capsys.readouterr().out
    record = records / "fig9" / "map10" / "tsne.npz"
    assert "tsne fig9: the t-SNE of 50 states, 4 panels" in out and record.is_file()
    arrays, meta = tsne.read_npz_record(record, tsne.TSNE_FORMAT)
    names = [p["name"] for p in meta["panels"]]
    assert names == ["raw state", "random projection (EMC)", "semu keys", "cnn_semu keys"]
    assert arrays["xy"].shape == (4, 50, 2) and meta["embeddings"] == {
        "semu": semu.id,
        "cnn_semu": cnn_semu.id,
    }
    assert campaign_main(["tsne", *args]) == 0 and capsys.readouterr().out == ""  # done: nothing again
    # the records alone draw it: no run directories
    outputs.rename(tmp_path / "gone")
    report = tmp_path / "report"
    assert report_main([str(records / "fig9"), "--out", str(report)]) == 0
    assert (report / "tsne.png").is_file()
    rows = (report / "tsne.md").read_text()
    assert all(f"| {name}" in rows for name in names)
    # a pruned memory run cannot be sampled: said in one line, exit status 1
    states.unlink()
    record.unlink()
    (tmp_path / "gone").rename(outputs)
    assert campaign_main(["tsne", *args]) == 1
    out = capsys.readouterr().out
    assert "failed: tsne fig9: " in out and "holds no episodic memory entries (pruned)" in out, out
