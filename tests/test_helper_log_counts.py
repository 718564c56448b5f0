"""A restarted helper's log lines in the stats (``processes.<helper>.log_lines`` and
``log_dropped``): the sum over its processes, and the table of counted processes no larger
than its helpers, with real spawned processes logging through ``logpipe.direct_stderr``."""

from __future__ import annotations

import logging
import multiprocessing

import pytest

from epc_offboard.common import procstats
from epc_offboard.common.children import join_or_kill, start_counted

pytestmark = pytest.mark.timeout(120)


def _logs(n: int) -> None:
    from epc_offboard.common import logpipe

    logging.getLogger().addHandler(logpipe.direct_stderr())
    for i in range(n):
        logging.getLogger("epc-test-helper").warning("line %d of %d", i + 1, n)


def test_a_helper_restarted_three_times_counts_every_process_lines_in_one_entry():
    ctx = multiprocessing.get_context("spawn")
    size = len(procstats._LOG_COUNTS)
    lines = [3, 5, 7, 11]  # the first process and three restarts
    pids = []
    for n in lines:
        proc = start_counted(ctx, _logs, (n,), "epc-test-helper")
        assert join_or_kill(proc, 60.0)  # it ends by itself: reaped
        assert proc.exitcode == 0
        assert proc.pid is not None
        pids.append(proc.pid)
        report = procstats.process_report(proc.pid)
        assert report["log_lines"] == sum(lines[: len(pids)]), (report, lines)
        assert report["log_dropped"] == 0
        assert len(procstats._LOG_COUNTS) == size + 1  # main: one entry more each restart
    other = start_counted(ctx, _logs, (2,), "epc-test-other")  # another helper: its own
    assert join_or_kill(other, 60.0)
    assert other.pid is not None
    assert procstats.process_report(other.pid)["log_lines"] == 2
    assert procstats.process_report(pids[-1])["log_lines"] == sum(lines)
    assert len(procstats._LOG_COUNTS) == size + 2
