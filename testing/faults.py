"""Faults injected into batch items, for tests and ``benchmarks.batch_faults``
only (never imported by the product): :func:`process_or_die` is put in
:attr:`service.batch.runner.BatchRunner.item_fn` from Python, so no request,
option or environment variable of a running server can reach it.

An item that kills its worker stands for a file that crashes a native
decoder (a segfault in LibRaw) or that the OOM killer ends: the worker
process dies with SIGKILL, abruptly, mid-item, and the pool breaks.
"""

from __future__ import annotations

import functools
import os
import signal
import time


def _process_or_die(names: frozenset, delay_s: float, task):
    if task.name in names:
        time.sleep(delay_s)          # as a decoder would, some way into the file
        os.kill(os.getpid(), signal.SIGKILL)
    from service.batch.items import process_item

    return process_item(task)


def process_or_die(names, delay_s: float = 0.3):
    """An item function (picklable: it runs in spawned pool workers) that
    processes every item as :func:`service.batch.items.process_item` does,
    except the items named in ``names``, whose worker process it kills
    (SIGKILL) ``delay_s`` seconds after they start, every time they run."""
    return functools.partial(_process_or_die, frozenset(names), float(delay_s))
