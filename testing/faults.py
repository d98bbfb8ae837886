"""Faults injected into batch items, for tests and ``benchmarks.batch_faults``
only (never imported by the product): :func:`process_or_die` is put in
:attr:`service.batch.runner.BatchRunner.item_fn` (and :func:`sample_or_die`
in ``sample_fn``, the shared light's per-image estimation) from Python, so
no request, option or environment variable of a running server can reach it.

An item that kills its worker stands for a file that crashes a native
decoder (a segfault in LibRaw) or that the OOM killer ends: the worker
process dies with SIGKILL, abruptly, mid-item, and the pool breaks.
"""

from __future__ import annotations

import functools
import os
import signal
import time


def _or_die(what: str, names: frozenset, delay_s: float, task, *args):
    if task.name in names:
        time.sleep(delay_s)          # as a decoder would, some way into the file
        os.kill(os.getpid(), signal.SIGKILL)
    from service.batch import items

    return getattr(items, what)(task, *args)


def process_or_die(names, delay_s: float = 0.3):
    """An item function (picklable: it runs in spawned pool workers) that
    processes every item as :func:`service.batch.items.process_item` does,
    except the items named in ``names``, whose worker process it kills
    (SIGKILL) ``delay_s`` seconds after they start, every time they run."""
    return functools.partial(_or_die, "process_item", frozenset(names), float(delay_s))


def sample_or_die(names, delay_s: float = 0.3):
    """The same for the shared light's per-image estimation
    (:func:`service.batch.items.estimation_sample`)."""
    return functools.partial(_or_die, "estimation_sample", frozenset(names), float(delay_s))
