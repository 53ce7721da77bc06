"""mcrs-report on small synthetic run directories whose numbers are known, and on a real saved buffer."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
from scipy import stats

from mcrs.experiment.config import Config
from mcrs.viz.learning_curves import confidence_half_width
from mcrs_lab.analysis.report import main as report_main
from mcrs_lab.analysis.runs import find_runs, run_labels, select_map
from mcrs_lab.analysis.tsne import return_locality

pytestmark = pytest.mark.slow

STEPS = [0, 10_000, 20_000, 30_000]
METRICS = ("episode_reward", "uncertainty", "collisions", "targets_found")


def make_run(
    root: Path,
    name: str,
    *,
    algo: str = "qmix",
    seed: int = 0,
    env: str = "map10",
    reward: list[float] | None = None,
    metrics: tuple[str, ...] = METRICS,
    steps: list[int] = STEPS,
    q_tot: list[float] | None = None,
    **settings: object,
) -> Path:
    """A run directory as mcrs-train writes it: the full config, CSV scalars, a checkpoints folder."""
    run = root / name
    config = OmegaConf.to_container(OmegaConf.structured(Config))
    config["env"] = {"name": env, "comm_range": 5.0, "max_steps": 50}
    config["algo"]["name"] = algo
    config["seed"] = seed
    for dotted, value in settings.items():
        node = config
        *parents, last = dotted.split("__")
        for part in parents:
            node = node[part]
        node[last] = value
    (run / "checkpoints").mkdir(parents=True)
    OmegaConf.save(OmegaConf.create(config), run / "config.yaml")
    reward = reward or [float(k + seed) for k in range(len(steps))]
    for metric in metrics:
        folder = run / "logs" / "scalars" / "eval"
        folder.mkdir(parents=True, exist_ok=True)
        values = reward if metric == "episode_reward" else [float(len(metric))] * len(steps)
        (folder / f"{metric}.csv").write_text(
            "".join(f"{s},{v}\n" for s, v in zip(steps, values, strict=True))
        )
    q_folder = run / "logs" / "scalars" / "train"
    q_folder.mkdir(parents=True, exist_ok=True)
    q_tot = q_tot or [s / 1000 for s in steps]
    (q_folder / "q_taken_mean.csv").write_text(
        "".join(f"{s},{q}\n" for s, q in zip(steps, q_tot, strict=True))
    )
    return run


def make_evaluation(root: Path, name: str, policy: str, comm_range: float, seed: int, found: float) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    with open(folder / "metrics.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            [
                "policy",
                "env",
                "comm_range",
                "seed",
                "episodes",
                "episode_reward_mean",
                "episode_reward_std",
                "targets_found_mean",
                "targets_found_std",
                "uncertainty_mean",
                "uncertainty_std",
            ]
        )
        writer.writerow(
            [policy, "map10", f"{comm_range:g}", seed, 4, 10 * found, 1, found, 0.5, 20 - found, 1]
        )
    return folder


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_confidence_half_width_is_student_t() -> None:
    values = np.array([[1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    expected = stats.t.ppf(0.975, 2) * 1.0 / np.sqrt(3)
    assert confidence_half_width(values) == pytest.approx([expected, 0.0])
    assert confidence_half_width(values[:1]).tolist() == [0.0, 0.0]  # one seed: no band


def test_seeds_are_averaged_per_method_and_heuristics_are_rows(tmp_path: Path) -> None:
    for seed in range(3):
        make_run(tmp_path, f"qmix_{seed}", seed=seed, reward=[0, 10 + seed, 20 + seed, 30 + 2 * seed])
        make_run(tmp_path, f"cnn_{seed}", algo="cnn_semu", seed=seed, algo__memory__enabled=True)
    for seed in range(2):
        make_evaluation(tmp_path, f"greedy_{seed}", "greedy", 5.0, seed, found=3 + seed)
    out = tmp_path / "report"
    assert report_main([str(tmp_path), "--out", str(out)]) == 0
    rows = {r["method"]: r for r in read_csv(out / "final.csv")}
    assert list(rows) == ["qmix", "cnn_semu", "greedy (heuristic)"]  # the paper's order, then heuristics
    assert float(rows["qmix"]["episode_reward_mean"]) == pytest.approx(32.0)  # (30 + 32 + 34) / 3
    assert float(rows["qmix"]["episode_reward_std"]) == pytest.approx(2.0)
    assert rows["qmix"]["seeds"] == "3" and rows["qmix"]["env_steps"] == "30000"
    assert float(rows["greedy (heuristic)"]["targets_found_mean"]) == pytest.approx(3.5)
    milestones = {r["method"]: r for r in read_csv(out / "milestones.csv")}
    assert float(milestones["qmix"]["reward_10000_mean"]) == pytest.approx(11.0)
    for figure in ("learning_curves.png", "q_tot.png"):
        assert (out / figure).stat().st_size > 10_000
    text = (out / "report.md").read_text()
    assert "6 training runs and 2 evaluation results read; 0 skipped" in text
    assert not (out / "table4.md").exists()  # delta was not swept
    versus = {(r["metric"], r["method"]): r for r in read_csv(out / "versus.csv")}  # each against greedy
    assert versus["episode_reward", "qmix"]["outcome"] == "level"  # 30-34 against 30 and 40
    assert (versus["targets_found", "qmix"]["outcome"], versus["targets_found", "qmix"]["since"]) == (
        "better",
        "0",
    )
    uncertainty = versus["uncertainty", "cnn_semu"]  # 11 against 17 and 16: two greedy seeds, p = 0.06
    assert (float(uncertainty["method_mean"]), float(uncertainty["heuristic_mean"])) == (11.0, 16.5)
    assert "| episode reward    | qmix     | level (p = " in (out / "versus.md").read_text()


def test_swept_settings_label_methods_and_delta_gives_table4(tmp_path: Path) -> None:
    for algo in ("emc", "cnn_semu"):
        for delta in (1.3e-3, 1.3e-1):
            for seed in range(2):
                make_run(
                    tmp_path,
                    f"{algo}_{delta}_{seed}",
                    algo=algo,
                    seed=seed,
                    env="map20",  # the paper's map: its table 4 stands beside ours
                    reward=[0.0, delta * 100, 2 + delta, 3.0 + (algo == "emc")],
                    algo__memory__enabled=True,
                    algo__memory__delta=delta,
                )
    make_run(tmp_path, "qmix", algo="qmix", env="map20")  # no memory: no delta label, no table-4 row
    # a point stopped at a session's end, its one seed short of the later columns
    make_run(
        tmp_path,
        "semu_stopped",
        algo="semu",
        env="map20",
        reward=[0.0, 5.0],
        steps=STEPS[:2],
        algo__memory__enabled=True,
        algo__memory__delta=1.3e-2,
    )
    runs = find_runs([tmp_path])
    assert sorted(set(run_labels(runs.training).values())) == [
        "cnn_semu delta=0.0013",
        "cnn_semu delta=0.13",
        "emc delta=0.0013",
        "emc delta=0.13",
        "qmix",
        "semu",
    ]
    out = tmp_path / "report"
    report_main([str(tmp_path), "--out", str(out)])
    table = read_csv(out / "table4.csv")
    assert [(r["delta"], r["algorithm"]) for r in table if r["seeds"] != "0"] == [
        ("0.0013", "emc"),
        ("0.0013", "cnn_semu"),
        ("0.013", "semu"),
        ("0.13", "emc"),
        ("0.13", "cnn_semu"),
    ]
    assert len(table) == 12  # and the paper's other rows (delta 1.3e-4 and 1.3e-2, SEMU), ours blank
    ours = [r for r in table if r["seeds"] != "0"]
    assert float(ours[3]["reward_10000"]) == pytest.approx(13.0)  # 0.13 * 100 at a third of 30k
    assert float(ours[3]["reward_30000"]) == pytest.approx(4.0)
    assert float(ours[3]["paper_2000000"]) == pytest.approx(311.41)  # the paper's EMC at delta 0.13
    md = (out / "table4.md").read_text()
    assert "| 0.13    | emc       |            2 | 13.00 ± 0.00 |" in md
    assert "| 0.013   | semu      | 1 (to 10.0k) |         5.00 |           - |           - |" in md


def test_table4_on_the_papers_map_needs_a_memory_run_not_a_sweep(tmp_path: Path) -> None:
    make_run(tmp_path, "qmix", algo="qmix", env="map20")
    out = tmp_path / "report"
    report_main([str(tmp_path), "--out", str(out)])
    assert not (out / "table4.md").exists()  # no memory method: nothing to set beside the paper's
    for seed in range(2):  # figure 7's runs: the default delta only
        make_run(tmp_path, f"semu_{seed}", algo="semu", seed=seed, env="map20", algo__memory__enabled=True)
    report_main([str(tmp_path), "--out", str(out)])
    table = read_csv(out / "table4.csv")
    assert [(r["delta"], r["algorithm"], r["seeds"]) for r in table if r["seeds"] != "0"] == [
        ("0.0013", "semu", "2")
    ]
    assert len(table) == 12  # the paper's other eleven rows, ours blank
    (semu,) = [r for r in table if r["seeds"] != "0"]
    assert float(semu["paper_666667"]) == pytest.approx(358.62)  # the paper's SEMU at delta 1.3e-3, 0.67M


def test_lambda_sweep_labels(tmp_path: Path) -> None:
    for weight in (0.01, 0.5):
        make_run(
            tmp_path, f"l{weight}", algo="cnn_semu", algo__memory_weight=weight, algo__memory__enabled=True
        )
    labels = run_labels(find_runs([tmp_path]).training)
    assert sorted(labels.values()) == ["cnn_semu lambda=0.01", "cnn_semu lambda=0.5"]


def test_a_learner_preset_labels_its_runs_by_its_name_and_what_differs_within_it(tmp_path: Path) -> None:
    """preset=pymarl2 sets seven fields: its runs are "qmix preset=pymarl2", not a list of those fields;
    a field swept within one preset (the learning rate here) still tells its runs apart."""
    pymarl2 = {"preset": "pymarl2", "train__optimizer": "adam", "algo__td_lambda": 0.6}
    make_run(tmp_path, "p1")
    make_run(tmp_path, "p2", **pymarl2, train__lr=1e-3)
    labels = run_labels(find_runs([tmp_path]).training)
    assert sorted(labels.values()) == ["qmix preset=pymarl", "qmix preset=pymarl2"]
    make_run(tmp_path, "p3", **pymarl2, train__lr=1e-4)
    labels = {path.name: label for path, label in run_labels(find_runs([tmp_path]).training).items()}
    assert labels == {
        "p1": "qmix preset=pymarl lr=0.0005",
        "p2": "qmix preset=pymarl2 lr=0.001",
        "p3": "qmix preset=pymarl2 lr=0.0001",
    }


def test_runs_of_older_code_are_seeds_of_the_same_method(tmp_path: Path) -> None:
    """A run recorded before a field existed (``env.comm_delay``, off by default) or after one was
    dropped (``env.device``) is a seed of the method it ran, not a method of its own; a run that sets
    the newer field to another value still is one."""
    old = make_run(tmp_path, "old", seed=0)
    config = OmegaConf.load(old / "config.yaml")
    config.env["device"] = None  # a field today's config no longer has
    OmegaConf.save(config, old / "config.yaml")
    make_run(tmp_path, "new", seed=1, env__comm_delay=0, train__checkpoint_minutes=5.0)
    make_run(tmp_path, "delayed", seed=2, env__comm_delay=2)
    labels = run_labels(find_runs([tmp_path]).training)
    assert {path.name: label for path, label in labels.items()} == {
        "old": "qmix comm_delay=0",
        "new": "qmix comm_delay=0",
        "delayed": "qmix comm_delay=2",
    }


def test_mixed_maps_are_skipped_with_the_reason(tmp_path: Path, capsys) -> None:
    make_run(tmp_path, "a", env="map10")
    make_run(tmp_path, "b", env="map10", seed=1)
    make_run(tmp_path, "c", env="map20")
    out = tmp_path / "report"
    report_main([str(tmp_path), "--out", str(out)])
    text = (out / "report.md").read_text()
    assert "# Report: map10" in text
    assert f"`{tmp_path / 'c'}`: map map20, the report is on map10 (pass --env to report it)" in text
    assert "skipped 1" in capsys.readouterr().out
    assert read_csv(out / "final.csv")[0]["seeds"] == "2"
    report_main([str(tmp_path), "--out", str(tmp_path / "r20"), "--env", "map20"])
    assert read_csv(tmp_path / "r20" / "final.csv")[0]["seeds"] == "1"


def test_many_runs_of_another_map_are_one_terminal_line_and_each_a_line_of_report_md(
    tmp_path: Path, capsys
) -> None:
    """A campaign's records folder holds every map: reporting one map must not print a line per run of
    the others, while report.md still names each skipped file."""
    make_run(tmp_path, "a", env="map10")
    others = [make_run(tmp_path, f"m20_{seed}", env="map20", seed=seed) for seed in range(4)]
    out = tmp_path / "report"
    report_main([str(tmp_path), "--out", str(out), "--env", "map10"])
    printed = capsys.readouterr().out.split("\nskipped ")[1]
    assert printed.startswith("4 ")
    assert "4 files (" in printed and printed.count("the report is on map10") == 1
    text = (out / "report.md").read_text()
    assert all(f"`{run}`: map map20, the report is on map10" in text for run in others)


def test_missing_metrics_skip_the_run_for_that_metric_only(tmp_path: Path) -> None:
    make_run(tmp_path, "full", seed=0)
    make_run(tmp_path, "partial", seed=1, metrics=("episode_reward",))
    out = tmp_path / "report"
    report_main([str(tmp_path), "--out", str(out)])
    text = (out / "report.md").read_text()
    assert f"`{tmp_path / 'partial'}`: no eval/uncertainty logged" in text
    row = read_csv(out / "final.csv")[0]
    assert row["seeds"] == "2"  # both runs count for the reward ...
    assert float(row["episode_reward_mean"]) == pytest.approx(3.5)
    assert (out / "learning_curves.png").is_file()  # ... and the figure is still made


def test_unreadable_and_foreign_directories_are_reported(tmp_path: Path) -> None:
    make_run(tmp_path, "good")
    bad = tmp_path / "bad"
    (bad / "checkpoints").mkdir(parents=True)
    (bad / "config.yaml").write_text("env: [unclosed\n")
    tb = make_run(tmp_path, "tb")
    for csv_file in (tb / "logs" / "scalars").rglob("*.csv"):
        csv_file.unlink()
    (tb / "logs" / "scalars" / "eval").rmdir()
    (tb / "logs" / "scalars" / "train").rmdir()
    (tb / "logs" / "scalars").rmdir()
    junk = make_run(tmp_path, "junk_events")
    for csv_file in (junk / "logs" / "scalars").rglob("*.csv"):
        csv_file.unlink()
    (junk / "logs" / "scalars" / "eval").rmdir()
    (junk / "logs" / "scalars" / "train").rmdir()
    (junk / "logs" / "scalars").rmdir()
    (junk / "logs" / "events.out.tfevents.1.host").write_bytes(b"not an event file")
    old = tmp_path / "old_eval"
    old.mkdir()
    (old / "metrics.csv").write_text("policy,env,episodes,episode_reward_mean\ngreedy,map10,4,1.0\n")
    runs = find_runs([tmp_path, tmp_path / "missing"])
    reasons = {s.path.name: s.reason for s in runs.skipped}
    assert reasons["bad"].startswith("config.yaml cannot be read")
    assert reasons["tb"] == "no metrics found (logger.backend=csv)"
    assert reasons["junk_events"] == "its TensorBoard event files hold no scalars"
    assert reasons["old_eval"] == "metrics.csv lacks comm_range, seed (rerun mcrs-eval)"
    assert reasons["missing"] == "no such file or directory"
    assert [r.path.name for r in runs.training] == ["good"]


def test_no_runs_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="mcrs-report: error: no readable runs of the paths"):
        report_main([str(tmp_path), "--out", str(tmp_path / "out")])
    make_run(tmp_path, "a")
    with pytest.raises(SystemExit, match="no readable runs of map map15"):
        report_main([str(tmp_path), "--out", str(tmp_path / "out"), "--env", "map15"])


def test_comm_range_from_evaluations(tmp_path: Path) -> None:
    for rc in (0.0, 5.0, 10.0):
        for seed in range(2):
            make_evaluation(tmp_path, f"g{rc}_{seed}", "greedy", rc, seed, found=rc / 5 + seed)
    out = tmp_path / "report"
    report_main([str(tmp_path), "--out", str(out)])
    rows = read_csv(out / "comm_range.csv")
    assert [(r["comm_range"], r["seeds"]) for r in rows] == [("0", "2"), ("5", "2"), ("10", "2")]
    assert [float(r["targets_found_mean"]) for r in rows] == pytest.approx([0.5, 1.5, 2.5])
    assert (out / "comm_range.png").is_file()


def test_comm_range_from_training_runs(tmp_path: Path) -> None:
    for rc in (0.0, 5.0):
        for seed in range(2):
            run = make_run(tmp_path, f"rc{rc}_{seed}", seed=seed, reward=[0, 1, 2, 10 * rc + seed])
            config = OmegaConf.load(run / "config.yaml")
            config.env.comm_range = rc
            OmegaConf.save(config, run / "config.yaml")
    out = tmp_path / "report"
    report_main([str(tmp_path), "--out", str(out)])
    rows = read_csv(out / "comm_range.csv")
    assert [r["policy"] for r in rows] == ["qmix (trained at R_c)"] * 2
    assert [float(r["episode_reward_mean"]) for r in rows] == pytest.approx([0.5, 50.5])
    assert {r["method"] for r in read_csv(out / "final.csv")} == {"qmix R_c=0", "qmix R_c=5"}


def test_return_locality_separates_related_from_unrelated() -> None:
    rng = np.random.default_rng(0)
    returns = rng.uniform(0, 10, 500)
    related = np.stack([returns, rng.normal(0, 0.01, 500)], axis=1)
    unrelated = rng.normal(size=(500, 2))
    assert return_locality(related, returns) < 0.1
    assert 0.8 < return_locality(unrelated, returns) < 1.2


def test_select_map_prefers_the_most_runs(tmp_path: Path) -> None:
    make_run(tmp_path, "a", env="map15")
    make_run(tmp_path, "b", env="map20")
    make_run(tmp_path, "c", env="map20", seed=1)
    runs = find_runs([tmp_path])
    assert select_map(runs, None) == "map20"
    assert [r.path.name for r in runs.training] == ["b", "c"]


def test_tsne_without_a_readable_buffer_is_reported_not_raised(tmp_path: Path) -> None:
    run = make_run(tmp_path, "cnn", algo="cnn_semu", algo__memory__enabled=True)
    (run / "checkpoints" / "last.pt").write_bytes(b"not a checkpoint")
    out = tmp_path / "report"
    assert report_main([str(tmp_path), "--out", str(out), "--tsne"]) == 0
    text = (out / "report.md").read_text()
    assert "## t-SNE of memory states (figure 9)\n\nnot made: checkpoint" in text
    assert (out / "final.csv").is_file()  # the rest of the report is still written


def test_trained_policies_on_fixed_episodes_count_once_per_trained_run(tmp_path: Path) -> None:
    """mcrs-eval of trained runs: a run's evaluation seeds are averaged first, then mean ± std over runs;
    runs that differ in more than their seed are separate methods."""
    for run, base in (("qmix_shield_seed0", 3.0), ("qmix_shield_seed1", 5.0), ("qmix_plain_seed0", 1.0)):
        for seed in range(2):
            make_evaluation(tmp_path, f"{run}_eval{seed}", f"outputs/x/{run}", 5.0, seed, found=base + seed)
    make_evaluation(tmp_path, "greedy_0", "greedy", 5.0, 0, found=2.0)
    out = tmp_path / "report"
    report_main([str(tmp_path), "--out", str(out)])
    rows = {r[0]: r[1:] for r in _table_rows((out / "report.md").read_text())}
    # qmix_shield: run means 3.5 and 5.5 -> 4.50 ± 1.41 (std over the two runs, not over four rows)
    assert rows["trained qmix_shield"][:2] == ["2", "-"]
    assert (
        rows["trained qmix_shield"][2] == "45.00 ± 14.14" and rows["trained qmix_shield"][5] == "4.50 ± 1.41"
    )
    assert rows["trained qmix_plain"][0] == "1" and rows["trained qmix_plain"][5].startswith("1.50")
    assert rows["greedy (heuristic)"][0] == "1"


def _table_rows(markdown_text: str) -> list[list[str]]:
    lines = [line for line in markdown_text.splitlines() if line.startswith("| ") and "---" not in line]
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in lines[1:]]


def test_one_seed_shows_no_spread_and_close_steps_get_distinct_headings(tmp_path: Path) -> None:
    """One seed: the mean alone (``± 0.00`` would claim a spread that was never measured). A run whose last
    evaluation comes right after the one before (11,200 then 11,240) keeps both columns apart: the
    headings get the decimals they need; a step nearest to two fractions is one column."""
    make_run(tmp_path, "qmix", reward=[1.0, 2.0, 3.0], steps=[0, 11_200, 11_240])
    out = tmp_path / "report"
    assert report_main([str(tmp_path), "--out", str(out)]) == 0
    final, milestones = (out / "final.md").read_text(), (out / "milestones.md").read_text()
    assert "±" not in final and "±" not in milestones

    def cells(line: str) -> list[str]:
        return [c.strip() for c in line.strip().strip("|").split("|")]

    assert cells(final.splitlines()[2])[:4] == ["qmix", "1", "11.2k", "3.00"]
    assert cells(milestones.splitlines()[0]) == ["method", "seeds", "0", "11.20k", "11.24k"]
    assert cells(milestones.splitlines()[2]) == ["qmix", "1", "1.00", "2.00", "3.00"]
    # Two seeds: the spread is shown again.
    make_run(tmp_path, "qmix_1", seed=1, reward=[1.0, 4.0, 5.0], steps=[0, 11_200, 11_240])
    assert report_main([str(tmp_path), "--out", str(out)]) == 0
    assert "4.00 ± 1.41" in (out / "milestones.md").read_text()


def test_marl_eval_export_has_marl_evals_structure(tmp_path: Path) -> None:
    """``--marl-eval``: environment -> map -> method -> run -> step_i (step_count, metric lists) plus
    absolute_metrics last; every map is a task (the report itself keeps one), the seeds are the runs."""
    import json

    for seed in range(2):
        make_run(tmp_path, f"qmix_{seed}", seed=seed, reward=[0.0, 10.0 + seed, 20.0, 30.0 + seed])
    make_run(tmp_path, "vdn", algo="vdn", reward=[1.0, 2.0], steps=[0, 10_000])  # shorter: its own steps
    make_run(tmp_path, "other_map", env="map20", steps=[0, 5_000])
    out = tmp_path / "report"
    assert report_main([str(tmp_path), "--out", str(out), "--marl-eval", str(out / "me.json")]) == 0
    data = json.loads((out / "me.json").read_text())
    assert list(data) == ["mcrs"] and sorted(data["mcrs"]) == ["map10", "map20"]
    assert sorted(data["mcrs"]["map10"]) == ["qmix", "vdn"]
    qmix = data["mcrs"]["map10"]["qmix"]
    assert list(qmix) == ["run_0", "run_1"]  # seed order
    run1 = qmix["run_1"]
    assert list(run1) == ["step_0", "step_1", "step_2", "step_3", "absolute_metrics"]  # absolute last
    assert run1["step_1"]["step_count"] == 10_000 and run1["step_1"]["episode_reward"] == [11.0]
    assert set(run1["step_1"]) == {"step_count", *METRICS}
    assert all(isinstance(v, list) and len(v) == 1 for k, v in run1["step_3"].items() if k != "step_count")
    assert run1["absolute_metrics"]["episode_reward"] == [31.0]
    # the file is never replaced by mistake: a second report refuses it without --force, and writes nothing
    (out / "me.json").write_text("mine")
    with pytest.raises(SystemExit, match=r"me\.json: the file exists; pass --force to replace it"):
        report_main([str(tmp_path), "--out", str(out), "--marl-eval", str(out / "me.json")])
    assert (out / "me.json").read_text() == "mine"
    assert (
        report_main([str(tmp_path), "--out", str(out), "--marl-eval", str(out / "me.json"), "--force"]) == 0
    )
    assert json.loads((out / "me.json").read_text()) == data
    assert [p.name for p in out.iterdir() if p.name.endswith(".tmp")] == []
    assert "step_count" not in run1["absolute_metrics"]
    assert list(data["mcrs"]["map10"]["vdn"]["run_0"]) == ["step_0", "step_1", "absolute_metrics"]


def test_a_seed_stopped_short_is_left_out_of_its_method_until_resumed(tmp_path: Path) -> None:
    """A campaign run stopped at a session's end must not drag its finished seeds back to its steps."""
    for seed in range(2):
        make_run(tmp_path, f"qmix_{seed}", seed=seed, reward=[0, 10, 20, 30 + seed])
    make_run(tmp_path, "qmix_2", seed=2, steps=STEPS[:2], reward=[0, 5])  # stopped at 10k
    out = tmp_path / "report"
    assert report_main([str(tmp_path), "--out", str(out)]) == 0
    (row,) = read_csv(out / "final.csv")
    assert row["seeds"] == "2" and row["env_steps"] == "30000"
    assert float(row["episode_reward_mean"]) == pytest.approx(30.5)
    assert "stopped at 10,000 env steps, short of its method's 30,000" in (out / "report.md").read_text()


def test_milestones_at_chosen_steps_take_the_nearest_evaluated_step(tmp_path: Path) -> None:
    """``--milestones 12k,28k``: the columns are the longest run's evaluated steps nearest to 12k and
    28k (10k and 30k); a method whose run ended earlier shows a dash past its end and how far it got."""
    steps = [0, 10_000, 20_000, 30_000]
    make_run(tmp_path, "qmix", reward=[1.0, 2.0, 3.0, 4.0], steps=steps)
    make_run(tmp_path, "vdn", algo="vdn", reward=[5.0, 6.0], steps=steps[:2])
    out = tmp_path / "report"
    assert report_main([str(tmp_path), "--out", str(out), "--milestones", "12k,28k"]) == 0
    rows = {r["method"]: r for r in read_csv(out / "milestones.csv")}
    assert float(rows["qmix"]["reward_10000_mean"]) == 2.0 and float(rows["qmix"]["reward_30000_mean"]) == 4.0
    assert "reward_20000_mean" not in rows["qmix"] and "reward_0_mean" not in rows["qmix"]
    assert float(rows["vdn"]["reward_10000_mean"]) == 6.0 and rows["vdn"]["reward_30000_mean"] == "nan"
    # A run that evaluates at slightly other steps (another num_envs) is read at its nearest evaluation.
    make_run(tmp_path, "qplex", algo="qplex", reward=[7.0, 8.0, 9.0], steps=[0, 9_000, 28_000])
    assert report_main([str(tmp_path), "--out", str(out), "--milestones", "12k,28k"]) == 0
    rows = {r["method"]: r for r in read_csv(out / "milestones.csv")}
    assert (
        float(rows["qplex"]["reward_30000_mean"]) == 9.0 and float(rows["qplex"]["reward_10000_mean"]) == 8.0
    )
    assert "the chosen env steps (--milestones)" in (out / "report.md").read_text()
    # the shorter run says how far it got, and the column past it is a dash
    assert "| vdn    | 1 (to 10.0k) |  6.00 |     - |" in (out / "milestones.md").read_text()


@pytest.mark.parametrize("bad", ["0", "-5k", "1.5", "abc", "10k,,20k", "0.0000005M"])
def test_bad_milestones_are_a_usage_error_naming_the_option(bad: str, tmp_path: Path, capsys) -> None:
    make_run(tmp_path, "qmix")
    with pytest.raises(SystemExit) as stopped:
        report_main([str(tmp_path), "--out", str(tmp_path / "report"), "--milestones", bad])
    assert stopped.value.code == 2
    assert "--milestones" in capsys.readouterr().err and not (tmp_path / "report").exists()
