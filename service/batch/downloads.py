"""Zip downloads of a batch in progress, and the removals that must wait
for them (probe round 4, fix 4 and its leftover).

``GET /v1/batches/{id}/zip`` opens the batch's results one after the other
while it streams, so a batch removed meanwhile (a user's ``DELETE
?remove=true``, or the runner's retention sweep,
``WANDELL_BATCH_RESULT_RETENTION``) cut the zip: the client got an
unreadable file after a 200. Both removals ask :meth:`Downloads.removing`
first, and the zip :meth:`Downloads.begin` s before it lists the results:
a batch being removed starts no download, and a batch being downloaded is
not removed (the DELETE is a 409 ``downloading``; the sweep postpones it to
a later pass).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator


class Downloads:
    """Per batch id: the zip downloads being sent now, and whether it is
    being removed. Thread-safe (the sweep runs in the runner's thread, the
    requests in the server's); the lock is held only to count, never while
    files are removed or sent."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sending: dict[str, int] = {}
        self._removing: set[str] = set()

    def begin(self, batch_id: str) -> bool:
        """Count one download of ``batch_id``; False (nothing counted) when
        the batch is being removed."""
        with self._lock:
            if batch_id in self._removing:
                return False
            self._sending[batch_id] = self._sending.get(batch_id, 0) + 1
            return True

    def end(self, batch_id: str) -> None:
        """One download of ``batch_id`` is sent or given up."""
        with self._lock:
            n = self._sending.get(batch_id, 0) - 1
            if n > 0:
                self._sending[batch_id] = n
            else:
                self._sending.pop(batch_id, None)

    def count(self, batch_id: str) -> int:
        """Downloads of ``batch_id`` being sent now."""
        with self._lock:
            return self._sending.get(batch_id, 0)

    @contextlib.contextmanager
    def removing(self, batch_id: str) -> Iterator[int]:
        """Around a removal of ``batch_id``: yields the downloads of it being
        sent now. 0: remove it; no download of it starts until the block
        ends. More: do not remove it (its results are being read)."""
        with self._lock:
            busy = self._sending.get(batch_id, 0)
            if not busy:
                self._removing.add(batch_id)
        try:
            yield busy
        finally:
            if not busy:
                with self._lock:
                    self._removing.discard(batch_id)
