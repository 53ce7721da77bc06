"""The torch thread count (``threads=auto``) and the oversubscription warning, decided from injected
cores, load and CPU times (no timing of this machine)."""

from __future__ import annotations

import logging

import pytest
import torch

from mcrs.experiment.util.threads import (
    SpeedCheck,
    auto_threads,
    oversubscription,
    resolve_threads,
    scheduler_times,
    threads_problem,
)


@pytest.mark.parametrize(
    ("cores", "load", "expected"),
    [
        (2, 0.0, 2),  # a quiet machine: every core
        (2, 0.3, 2),
        (2, 0.6, 1),  # a core mostly busy: leave it
        (2, 2.0, 1),  # two other trainings on two cores: one thread, never zero
        (2, 7.5, 1),
        (16, 3.2, 13),
        (16, 0.0, 16),
        (1, 0.0, 1),
        (4, -1.0, 4),  # never more than the cores
    ],
)
def test_auto_takes_the_cores_the_load_leaves_free(cores: int, load: float, expected: int) -> None:
    assert auto_threads(cores, load) == expected


def test_resolve_threads_keeps_an_explicit_count_and_zero() -> None:
    assert resolve_threads("auto", 8, 6.0) == 2
    assert resolve_threads("3", 8, 6.0) == 3  # explicit: the load does not change it
    assert resolve_threads(1, 8, 0.0) == 1
    assert resolve_threads("0", 8, 0.0) == 0  # torch's default, left alone


@pytest.mark.parametrize("value", ["auto", "0", "1", "2", 2])
def test_allowed_thread_settings(value: object) -> None:
    assert threads_problem(value, cores=2) is None


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("all", "allowed values are auto (the cores the load leaves free), 0 (torch's default"),
        ("-1", "allowed values are auto"),
        ("1.5", "allowed values are auto"),
        ("3", "this machine has 2 CPU cores: use auto"),
    ],
)
def test_refused_thread_settings_name_the_allowed_values(value: str, message: str) -> None:
    problem = threads_problem(value, cores=2)
    assert problem is not None and message in problem


def test_no_warning_when_the_threads_got_their_cpu() -> None:
    # quiet: 30 s of wall clock, 29 s on a CPU, 1 s waiting for one
    assert oversubscription(30.0, 29.0, 1.0, threads=2, load=0.5, cores=2) is None
    # no scheduler statistics: one busy thread's worth of CPU time is enough
    assert oversubscription(30.0, 28.0, None, threads=1, load=1.0, cores=2) is None


def test_warning_names_the_wait_the_load_and_the_advice() -> None:
    warning = oversubscription(30.0, 12.0, 18.0, threads=2, load=3.9, cores=2)
    assert warning is not None
    assert "waited for a CPU 60% of the time" in warning
    assert "load average 3.9 on 2 cores, threads=2" in warning
    assert "use threads=1" in warning
    # one thread already: fewer jobs is the only advice
    warning = oversubscription(30.0, 10.0, 20.0, threads=1, load=4.0, cores=2)
    assert warning is not None and "fewer jobs at a time" in warning


def test_without_scheduler_statistics_the_cpu_share_decides() -> None:
    warning = oversubscription(30.0, 9.0, None, threads=2, load=4.2, cores=2)
    assert warning is not None and "0.30 CPU-seconds per second" in warning
    assert oversubscription(0.0, 0.0, None, threads=1, load=0.0, cores=2) is None  # nothing measured yet


def test_the_boundary_of_the_wait_share() -> None:
    assert oversubscription(30.0, 20.0, 10.0, 1, 1.0, 2) is None  # exactly a third: still fine
    assert oversubscription(30.0, 19.0, 11.0, 1, 1.0, 2) is not None


def test_speed_check_measures_once_and_logs_once(caplog) -> None:
    calls: list[tuple] = []

    def decide(*args):  # the decision is tested above; here: asked once, with the window's numbers
        calls.append(args)
        return "the machine is oversubscribed: (test)"

    check = SpeedCheck(threads=2, window_s=0.0, decide=decide)
    with caplog.at_level(logging.WARNING, logger="mcrs.experiment.util.threads"):
        for _ in range(5):
            check.observe()
    assert len(calls) == 1
    wall, cpu, _wait, n, load, cores = calls[0]
    assert wall >= 0 and cpu >= 0 and n == 2 and load >= 0 and cores >= 1
    assert [r.getMessage() for r in caplog.records] == ["the machine is oversubscribed: (test)"]
    assert check.done and check.warning == "the machine is oversubscribed: (test)"


def test_speed_check_waits_for_its_window_and_can_be_off() -> None:
    def decide(*args):
        raise AssertionError("measured too early")

    early = SpeedCheck(threads=1, window_s=3600.0, decide=decide)
    early.observe()
    assert not early.done
    off = SpeedCheck(threads=1, enabled=False, window_s=0.0, decide=decide)
    off.observe()
    assert off.warning is None


def test_scheduler_times_count_this_process_threads() -> None:
    times = scheduler_times()
    if times is None:  # not Linux: the CPU share is used instead
        return
    before = times
    torch.ones(200, 200).matmul(torch.ones(200, 200)).sum().item()
    after = scheduler_times()
    assert after is not None and after[0] >= before[0] > 0 and after[1] >= 0
