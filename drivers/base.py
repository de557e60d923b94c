"""What the drivers share: the context-manager lifecycle and the queue behind a streaming vehicle link.

:class:`Driver` is the base of every driver class: ``with driver:`` calls :meth:`Driver.open` and
:meth:`Driver.close`. :class:`QueuedVehicleLink` is the base of the links whose receive thread
decodes a byte stream (``serial://``, ``mavlink+…://``): the thread puts
:class:`robotd.core.msgs.Odometry` samples into one bounded drop-oldest queue and the consumer iterates
:meth:`QueuedVehicleLink.odometry`. :class:`ControlSample` is the commanded throttle/steering both
of those links report.
"""

from __future__ import annotations

import abc
import ipaddress
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Self

from robotd.core.msgs import Odometry
from robotd.formats.queues import DropOldestQueue


@dataclass(frozen=True, slots=True)
class ControlSample:
    """Latest commanded throttle and steering, each normalised to [-1, 1] (+steering = turn right).

    ``t_ns`` is on the host monotonic clock. ``source`` names the message it came from:
    ``"CONTROL_INPUTS"`` (the MCU over ``serial://``), ``"SERVO_OUTPUT_RAW"`` or ``"RC_CHANNELS"``
    (MAVLink, normalised from PWM as (pwm − 1500)/500).
    """

    t_ns: int
    throttle: float
    steering: float
    source: str


class Driver(abc.ABC):
    """Context-manager lifecycle of a driver: ``__enter__`` calls :meth:`open` and returns the
    driver, ``__exit__`` calls :meth:`close`."""

    url: str

    def open(self) -> None:  # noqa: B027 - a deliberate no-op: replay and none:// hold no device
        """Acquire the device, or raise :class:`robotd.core.errors.DriverError` with the URL."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device; a ``frames()``/``odometry()`` iterator running on another thread returns."""

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class QueuedVehicleLink(Driver):
    """A vehicle link fed by a receive thread through a bounded drop-oldest odometry queue.

    Subclasses start their threads in ``open()`` (after ``self._stop.clear()``), hand samples to
    :meth:`_emit`, keep the newest :class:`ControlSample` in ``self._controls``, and stop their
    threads and release the port in :meth:`_release`. ``counters`` is the subclass's stats dict:
    :meth:`_emit` counts ``"odometry"`` (every sample) and ``"drops"`` (oldest dropped) in it.
    """

    def __init__(self, url: str, queue_size: int, counters: dict[str, int]) -> None:
        self.url = url
        self._queue: DropOldestQueue[Odometry] = DropOldestQueue(queue_size)
        self._stop = threading.Event()
        self._controls: ControlSample | None = None
        self._odometry_counters = counters

    def close(self) -> None:
        self._stop.set()
        self._release()
        self._queue.close()  # last: wakes a consumer waiting in odometry() once the threads are gone

    @abc.abstractmethod
    def _release(self) -> None:
        """Stop the I/O threads (``self._stop`` is already set) and close the port."""

    def _emit(self, odo: Odometry) -> None:
        # producers never block: a slow consumer loses the oldest sample, counted
        if not self._queue.put(odo):
            self._odometry_counters["drops"] += 1
        self._odometry_counters["odometry"] += 1

    def odometry(self, timeout_s: float = 1.0) -> Iterator[Odometry]:
        """Yield odometry samples (FRD body velocity + body rates, host clock) as they arrive.

        Returns only when :meth:`close` is called: a quiet or reconnecting link keeps the
        iterator waiting (checking for close every ``timeout_s``), like a hardware camera.
        """
        while not self._stop.is_set():
            item = self._queue.get(timeout_s)
            if item is not None:
                yield item

    def drain(self) -> list[Odometry]:
        """Everything queued so far, oldest first, without waiting."""
        return self._queue.drain()

    def latest_controls(self) -> ControlSample | None:
        """The last throttle/steering the vehicle reported, or None."""
        return self._controls


def is_loopback(host: str) -> bool:
    """``host`` names this machine only (``localhost``, 127.0.0.0/8, ::1): what a link may listen
    on without the user's explicit permission to face the network."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
