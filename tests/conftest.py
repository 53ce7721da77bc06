"""Test-session settings."""

from pathlib import Path

import torch
from hypothesis import settings

# The suite steps small batches: one thread avoids thread start-up and contention costs on shared 2-core
# machines, where the second thread makes small ops slower, not faster.
torch.set_num_threads(1)

# Property tests draw the same examples on every run, so CI is reproducible; run with
# `--hypothesis-profile=explore` to draw new random examples.
settings.register_profile("ci", derandomize=True, deadline=None)
settings.register_profile("explore", deadline=None)
settings.load_profile("ci")

#: Modules whose tests train, launch processes or run benchmarks: ``make test-slow`` (CI runs it after
#: ``make test``). Everything else is the fast set ``make test`` runs.
SLOW_MODULES = {
    "test_benchmark_checkpoint.py",
    "test_benchmark_cli.py",
    "test_benchmark_learner.py",
    "test_benchmark_memory.py",
    "test_benchmark_overhead.py",
    "test_benchmark_resources.py",
    "test_campaign.py",
    "test_collector_workers.py",
    "test_crash_safety.py",
    "test_experiment_api.py",
    "test_example_api.py",
    "test_experiments.py",
    "test_ray_launcher.py",
    "test_interop_logging.py",
    "test_interrupt.py",
    "test_memory_training.py",
    "test_quickstart.py",
    "test_records.py",
    "test_report.py",
    "test_run_dirs.py",
    "test_training.py",
    "test_untrusted_files.py",
    "test_vmas_navigation.py",
}
#: Slow tests in otherwise fast modules (``module::test``).
SLOW_TESTS = {
    "test_bad_inputs_tools.py::test_resuming_a_finished_run_three_times_leaves_one_final_evaluation_row",
    "test_bad_inputs_tools.py::test_a_foreign_replay_block_is_refused_on_resume",
    "test_bad_inputs_tools.py::test_the_issues_2_4_gb_zip_bomb_is_refused_at_once",
    "test_cli_errors.py::test_refused_commands_print_one_line_of_ours_and_leave_no_directory",
    "test_cli_errors.py::test_hydra_full_error_still_gives_hydras_trace",
    "test_doc_tables.py::test_results_md_agrees_with_the_committed_records",
    "test_env_variants.py::test_variant_matches_the_slow_reference_on_larger_maps",
    "test_evaluate.py::test_cli_runs_and_prints_table",
    "test_evaluate.py::test_evaluations_started_together_get_their_own_directories",
    "test_evaluate.py::test_cli_unknown_policy_lists_allowed_names",
    "test_evaluate.py::test_cli_bad_env_field_is_one_clear_message_without_traceback",
    "test_reliability_config.py::test_cli_refuses_the_values_that_used_to_crash_late",
    "test_render.py::test_mcrs_render_cli_writes_the_pictures_into_out_only",
    "test_render.py::test_mcrs_render_cli_bad_input_is_one_line_without_traceback",
    "test_replay_store.py::test_time_based_checkpoints_and_the_replay_beside_last_pt",
    "test_resource_estimate.py::test_the_replay_estimate_is_the_bytes_a_full_buffer_holds",
    "test_trained_policy.py::test_checkpoint_policy_matches_the_training_greedy_policy",
}


def pytest_collection_modifyitems(config, items) -> None:
    """Mark the slow set (``-m slow``); the names above must exist, so the lists cannot rot."""
    import pytest

    seen_modules, seen_tests = set(), set()
    for item in items:
        name = f"{item.path.name}::{item.originalname}"
        seen_modules.add(item.path.name)
        seen_tests.add(name)
        if item.path.name in SLOW_MODULES or name in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)
    every_module = {path.name for path in Path(__file__).parent.glob("test_*.py")}
    whole_run = every_module <= seen_modules  # only a collection of every module can judge
    stale = (SLOW_MODULES - seen_modules) | (SLOW_TESTS - seen_tests) if whole_run else set()
    if stale:
        raise pytest.UsageError(f"tests/conftest.py names slow tests that do not exist: {sorted(stale)}")
