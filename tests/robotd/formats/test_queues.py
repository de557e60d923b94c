"""Drop-oldest queues (robotd.formats.queues): count what they drop, never block the producer."""

from __future__ import annotations

import threading
import time

import pytest

from robotd.formats.queues import DropOldestQueue


def test_drop_oldest_queue_counts_and_never_blocks() -> None:
    q: DropOldestQueue[int] = DropOldestQueue(3)
    for i in range(10):
        q.put(i)
    assert q.dropped == 7 and q.drain() == [7, 8, 9]
    assert q.get(timeout=0.01) is None
    got: list[int | None] = []
    th = threading.Thread(target=lambda: got.append(q.get(timeout=5)))
    th.start()
    time.sleep(0.05)
    q.close()
    th.join(1)
    assert not th.is_alive() and got == [None]
    with pytest.raises(ValueError):
        DropOldestQueue(0)
