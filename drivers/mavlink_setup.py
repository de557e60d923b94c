"""What the MAVLink link asks of the autopilot, and what the autopilot says back about it: its EKF
origin (``SET_GPS_GLOBAL_ORIGIN``, checked and sent again while it is gone), the message rates
(``MAV_CMD_SET_MESSAGE_INTERVAL``, one request at a time, each matched with its ``COMMAND_ACK``:
:class:`drivers.mavlink_guard.RateRequests`) and a vision-yaw alignment (``MAV_CMD_DO_AUX_FUNCTION``
80) when ArduPilot's pre-arm check says its vision yaw is off and the vehicle stands still.

The transmit thread of drivers/mavlink_link.py sends (:meth:`VehicleSetup.start`,
:meth:`VehicleSetup.send_rate_request`, :meth:`VehicleSetup.check_origin`,
:meth:`VehicleSetup.align_yaw`); its receive thread hands over the autopilot's answers
(:meth:`VehicleSetup.handlers`). No pymavlink here
(drivers/mavlink_link.py is its only importer): the dialect module is given, ``m``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from drivers.mavlink_guard import NO_ACK, RateOutcome, RateRequests
from drivers.mavlink_options import MavlinkOptions

logger = logging.getLogger("drivers.mavlink_link")  # the link's lines, under the link's one name

ORIGIN_CHECK_S = 2.0  # how often the autopilot's EKF origin is checked (and sent again if it is gone)
ALIGN_STILL_S = 2.0  # the vehicle stood still this long before robotd asks for a vision-yaw alignment
ALIGN_INTERVAL_S = 5.0  # ... and at most this often
AUX_FUNCTION_VISO_ALIGN = 80  # ArduPilot's RC aux function "VisOdom align"
# what to tell the user when the autopilot refuses a rate request for these messages
RATE_HINTS = {
    "WHEEL_DISTANCE": "ArduPilot streams it only with wheel encoders (WENC_TYPE) in its EXTRA1 group "
    "(MAVn_EXTRA1, SRn_EXTRA1 before 4.7): docs/mavlink.md §3",
}


@dataclass
class Autopilot:
    """What the link knows of the autopilot, from its heartbeats (the receive thread writes)."""

    sysid: int | None = None  # None until its first heartbeat
    compid: int = 1
    addr: tuple[str, int] | None = None  # where its heartbeat came from (UDP)
    link_up: bool = False  # its heartbeat came within the link timeout
    armed: bool | None = None


@dataclass(frozen=True)
class SetupLink:
    """What the setup uses of its link."""

    peer: Autopilot  # the autopilot as the link knows it
    request: Callable[[str, Any], None]  # queue a send for the transmit thread (here "align_yaw")
    wake: threading.Event  # wakes the transmit thread (the next rate request may leave)
    still_for_s: Callable[[], float]  # how long the vehicle has stood still (the pose role's measure)
    our_sysid: Callable[[], int]  # the system id the link speaks as (0 before it is open)


class VehicleSetup:
    """The origin, the message rates and the yaw alignment (module docstring). ``counters``: the
    link's counter dict; ``m``: the MAVLink dialect module."""

    def __init__(self, url: str, opts: MavlinkOptions, counters: dict[str, int], m: Any, link: SetupLink) -> None:
        self.url, self.opts, self.c, self.m = url, opts, counters, m
        self.link = link
        self.peer = link.peer
        self._lock = threading.Lock()  # guards rates (ACKs arrive on the receive thread)
        self.rates = RateRequests()
        self.ekf_flags: int | None = None
        self.origin_confirmed = False
        self._origin_heard = False  # a GPS_GLOBAL_ORIGIN with our origin since the last check
        self._last_align_mono = -math.inf
        self.last_visodom_text = ""
        self._next_origin_check = math.inf

    def handlers(self) -> dict[str, Callable[[Any, int], None]]:
        """Message type -> handler(msg, arrival t_ns), for the autopilot's messages."""
        return {
            "EKF_STATUS_REPORT": self.on_ekf_status_report,
            "GPS_GLOBAL_ORIGIN": self.on_gps_global_origin,
            "STATUSTEXT": self.on_statustext,
            "COMMAND_ACK": self.on_command_ack,
        }

    # -- receive -------------------------------------------------------------------------------
    def on_ekf_status_report(self, msg: Any, t_ns: int) -> None:
        self.ekf_flags = int(msg.flags)

    def on_gps_global_origin(self, msg: Any, t_ns: int) -> None:
        o = self.opts.origin
        if o is None:
            self.origin_confirmed = True
            return
        # ours, to the message's resolution (1e-7 deg); another origin is not a confirmation
        ours = (round(o[0] * 1e7), round(o[1] * 1e7))
        match = (int(msg.latitude), int(msg.longitude)) == ours
        self.origin_confirmed = match
        self._origin_heard = self._origin_heard or match
        if not match:
            logger.warning(
                "%s: the autopilot's EKF origin is (%.7f, %.7f), not the configured one",
                self.url,
                msg.latitude * 1e-7,
                msg.longitude * 1e-7,
            )

    def on_statustext(self, msg: Any, t_ns: int) -> None:
        """ArduPilot's pre-arm "VisOdom: yaw diff …" (its vision yaw, rotated onto its own heading
        when it aligned them, no longer agrees with that heading): once the vehicle has stood
        still for ALIGN_STILL_S, robotd asks it to align again (MAV_CMD_DO_AUX_FUNCTION, function
        80), at most every ALIGN_INTERVAL_S and never while armed; an alignment taken while the
        rover turned, or before the compass settled, is what left it off (docs/mavlink.md §6)."""
        text = str(msg.text)
        if "VisOdom:" not in text:
            return
        self.last_visodom_text = text
        if "yaw diff" not in text or not self.opts.align_yaw or self.peer.armed is not False:
            return
        now = time.monotonic()
        if now - self._last_align_mono < ALIGN_INTERVAL_S:
            return
        if self.link.still_for_s() < ALIGN_STILL_S:
            return
        self._last_align_mono = now
        logger.info(
            "%s: the autopilot says %r and the vehicle is still: asking it to align its vision yaw "
            "to its own heading (aux function %d)",
            self.url,
            text,
            AUX_FUNCTION_VISO_ALIGN,
        )
        self.link.request("align_yaw", text)

    def on_command_ack(self, msg: Any, t_ns: int) -> None:
        """An answer to one of our SET_MESSAGE_INTERVAL requests (the outstanding one: the ACK
        does not say which message it concerns, drivers.mavlink_guard.RateRequests)."""
        if msg.command != self.m.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        # MAVLink 2 ACKs name whom they answer (0 when not filled in): another requester's is not ours
        ours = (0, self.link.our_sysid()), (0, self.opts.compid)
        if getattr(msg, "target_system", 0) not in ours[0] or getattr(msg, "target_component", 0) not in ours[1]:
            return
        with self._lock:
            outcome = self.rates.on_ack(int(msg.result))
            self._count_rates()
        if outcome is not None:
            self._log_rate(outcome)
            self.link.wake.set()  # the next request may leave now

    def on_reboot(self) -> None:
        """The autopilot rebooted: its EKF origin is gone (the link sends the setup again)."""
        self.origin_confirmed = False

    # -- transmit ------------------------------------------------------------------------------
    def start(self, mav: Any) -> None:
        """Once the autopilot is known, and after each of its reboots: the origin, then the rates."""
        self.send_origin(mav)
        if self.opts.request_rates:
            with self._lock:
                self.rates.start(self.opts.rates_hz)

    def align_yaw(self, mav: Any) -> None:
        self._command(mav, self.m.MAV_CMD_DO_AUX_FUNCTION, AUX_FUNCTION_VISO_ALIGN, 2)  # switch high
        self.c["yaw_align_requests"] += 1

    def check_origin(self, mav: Any, now: float) -> None:
        """Keep the EKF origin set: ArduPilot's EKF3 forgets an origin set before it initialised
        (measured in SITL: "origin set", then the EKF started, then no origin, and a mission in
        AUTO waits for one for ever). Every ORIGIN_CHECK_S robotd asks for GPS_GLOBAL_ORIGIN
        (MAV_CMD_REQUEST_MESSAGE); when no matching one came since the last check, the origin is
        sent again (``origins_sent`` counts every send)."""
        if now < self._next_origin_check:
            return
        self._next_origin_check = now + ORIGIN_CHECK_S
        if not self.peer.link_up or self.peer.sysid is None:
            return
        if not self._origin_heard:
            self.origin_confirmed = False
            self.send_origin(mav)
        self._origin_heard = False
        self._command(mav, self.m.MAV_CMD_REQUEST_MESSAGE, self.m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
        self.c["origin_requests"] += 1

    def send_origin(self, mav: Any) -> None:
        if self.opts.origin is None or self.peer.sysid is None:
            return
        if self._next_origin_check == math.inf:
            self._next_origin_check = time.monotonic() + ORIGIN_CHECK_S
        lat, lon, alt = self.opts.origin
        mav.set_gps_global_origin_send(
            self.peer.sysid, round(lat * 1e7), round(lon * 1e7), round(alt * 1000), time.monotonic_ns() // 1000
        )
        self.c["origins_sent"] += 1
        logger.info("%s: EKF origin sent (%.7f, %.7f, %.2f m)", self.url, lat, lon, alt)

    def send_rate_request(self, mav: Any) -> None:
        """The next SET_MESSAGE_INTERVAL request, once the previous one was answered (or timed out)."""
        with self._lock:
            req, timed_out = self.rates.next_request(time.monotonic_ns())
            done = self.rates.round_finished()
            self._count_rates()
        if timed_out is not None:
            self._log_rate(timed_out)
        if done:
            self._log_rates_done()
        if req is None:
            return
        name, hz = req
        interval_us = -1 if hz <= 0 else round(1e6 / hz)  # -1 disables the message
        self._command(mav, self.m.MAV_CMD_SET_MESSAGE_INTERVAL, getattr(self.m, f"MAVLINK_MSG_ID_{name}"), interval_us)
        self.c["rate_requests"] += 1

    def _command(self, mav: Any, command: int, p1: float, p2: float = 0) -> None:
        """COMMAND_LONG to the autopilot (system 1 until its heartbeat names it), the rest of the
        parameters 0."""
        mav.command_long_send(self.peer.sysid or 1, self.peer.compid, command, 0, p1, p2, 0, 0, 0, 0, 0)

    # -- counts and logs -----------------------------------------------------------------------
    def _count_rates(self) -> None:
        r = self.rates
        self.c["rates_accepted"], self.c["rates_refused"] = r.accepted, r.refused
        self.c["rates_unacknowledged"] = r.unacknowledged

    def rate_stats(self) -> dict[str, Any]:
        """This round's requests for stats(): the refused ones (and those never answered) as
        ``NAME RATE Hz: MAV_RESULT``, and the granted rates."""
        with self._lock:
            refusals, granted = list(self.rates.refusals), dict(self.rates.granted)
        return {
            "rates_refused_messages": [f"{o.name} {o.hz:g} Hz: {self._result_name(o.result)}" for o in refusals],
            "rates_granted": [f"{name} {hz:g} Hz" for name, hz in granted.items()],
        }

    def _log_rate(self, o: RateOutcome) -> None:
        """One line per request that was not granted; nothing for one that was."""
        what = f"{self.url}: SET_MESSAGE_INTERVAL {o.name} at {o.hz:g} Hz"
        if o.result == NO_ACK:
            logger.warning(
                "%s: no COMMAND_ACK within %.1f s (counted in rates_unacknowledged)", what, self.rates.ack_timeout_s
            )
        elif o.result == self.m.MAV_RESULT_ACCEPTED:
            if o.was_retry:
                logger.info("%s accepted", what)
        elif o.retry_hz is not None:
            logger.warning(
                "%s refused by the autopilot (%s); asking for %g Hz instead",
                what,
                self._result_name(o.result),
                o.retry_hz,
            )
        else:
            hint = RATE_HINTS.get(o.name)
            logger.warning(
                "%s refused by the autopilot (%s)%s; not asked again: it comes at the autopilot's rate, if at all%s",
                what,
                self._result_name(o.result),
                " too" if o.was_retry else "",
                f" ({hint})" if hint else "",
            )

    def _log_rates_done(self) -> None:
        st = self.rate_stats()
        logger.info(
            "%s: message rates granted: %s%s",
            self.url,
            ", ".join(st["rates_granted"]) or "none",
            f"; refused: {', '.join(st['rates_refused_messages'])}" if st["rates_refused_messages"] else "",
        )

    def _result_name(self, result: int) -> str:
        """MAV_RESULT_DENIED for 2, ...; "no ACK" for a request never answered."""
        if result == NO_ACK:
            return "no ACK"
        entry = self.m.enums["MAV_RESULT"].get(result)
        return entry.name if entry is not None else f"MAV_RESULT {result}"
