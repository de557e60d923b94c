"""What the MAVLink link believes, and how much it answers: pure helpers (no pymavlink, no I/O).

- :class:`RateLimit`: a token bucket; TIMESYNC replies are rate-limited with it, so a flood of
  requests (7,376 of them in the fault campaign) gets a bounded number of replies.
- :class:`BootClock`: reboot detection from ``SYSTEM_TIME.time_boot_ms``. One message whose boot
  time falls is not a reboot (567 spoofed SYSTEM_TIMEs once counted as 192 reboots, each
  re-sending the EKF origin and the rate requests). Each sample is turned into the host time at
  which the autopilot booted, ``b = t_arrival − time_boot_ms``; the autopilot's own samples agree
  on ``b`` to within the transport jitter. A new boot clock is adopted only when

  1. at least ``min_samples`` samples agree on it (within ``tolerance_s``),
  2. an autopilot HEARTBEAT arrived after its first sample,
  3. the established clock has not been heard for ``quiet_s`` since that first sample (the old
     autopilot is not still talking), and

  it is a reboot when the new boot instant is more than ``min_jump_s`` after the old one (the
  autopilot booted again later). The first clock is established by ``min_samples`` agreeing
  samples, without counting a reboot.
- :class:`RateRequests`: the MAV_CMD_SET_MESSAGE_INTERVAL requests, one outstanding at a time so
  that each COMMAND_ACK (which does not say which message it answers) is matched to its request;
  a refused rate is retried once at half the rate. The autopilot's refusals were once silent
  (ArduPilot Rover refuses ATTITUDE at 50 Hz and any WHEEL_DISTANCE request, issue 24).
"""

from __future__ import annotations

from dataclasses import dataclass, field


class RateLimit:
    """Token bucket: at most ``rate_hz`` events a second on average, ``burst`` at once.
    ``rate_hz <= 0`` allows nothing."""

    def __init__(self, rate_hz: float, burst: float | None = None) -> None:
        self.rate_hz = float(rate_hz)
        self.burst = float(burst if burst is not None else max(1.0, self.rate_hz))
        self._tokens = self.burst
        self._t_ns: int | None = None
        self.allowed = 0
        self.refused = 0

    def allow(self, now_ns: int) -> bool:
        if self._t_ns is not None and now_ns > self._t_ns:
            self._tokens = min(self.burst, self._tokens + (now_ns - self._t_ns) * 1e-9 * self.rate_hz)
        self._t_ns = now_ns if self._t_ns is None else max(self._t_ns, now_ns)
        if self.rate_hz > 0 and self._tokens >= 1.0:
            self._tokens -= 1.0
            self.allowed += 1
            return True
        self.refused += 1
        return False


@dataclass
class _Clock:
    boot_ns: float  # host time of the autopilot's boot, mean of the samples
    first_ns: int  # arrival of the first sample
    last_ns: int  # arrival of the latest sample
    n: int = 1
    heartbeat_after_first: bool = False

    def add(self, boot_ns: float, t_ns: int) -> None:
        self.boot_ns += (boot_ns - self.boot_ns) / (self.n + 1)
        self.n += 1
        self.last_ns = t_ns


@dataclass
class BootClock:
    """Reboot detection from SYSTEM_TIME (module docstring). Feed it only messages that passed the
    link's source checks (the autopilot's system and component id, from its address)."""

    tolerance_s: float = 0.3
    min_samples: int = 2
    quiet_s: float = 1.5
    min_jump_s: float = 1.0
    expire_s: float = 10.0
    max_candidates: int = 4
    current: _Clock | None = None
    candidates: list[_Clock] = field(default_factory=list)
    reboots: int = 0
    mismatches: int = 0  # samples that fit no known clock (spoofed, corrupt, or a reboot's first)

    def heartbeat(self, t_ns: int) -> None:
        """An autopilot HEARTBEAT arrived at ``t_ns``."""
        for c in self.candidates:
            if t_ns > c.first_ns:
                c.heartbeat_after_first = True

    def observe(self, time_boot_ms: int, t_ns: int) -> bool:
        """One SYSTEM_TIME sample (``time_boot_ms``, arrival ``t_ns``); True when it confirms a reboot."""
        b = float(t_ns) - float(time_boot_ms) * 1e6
        tol = self.tolerance_s * 1e9
        self.candidates = [c for c in self.candidates if t_ns - c.last_ns <= self.expire_s * 1e9]
        cur = self.current
        if cur is not None and abs(b - cur.boot_ns) <= tol:
            cur.add(b, t_ns)
            return False
        self.mismatches += cur is not None
        match = next((c for c in self.candidates if abs(b - c.boot_ns) <= tol), None)
        if match is None:
            self.candidates.append(_Clock(b, t_ns, t_ns))
            del self.candidates[: -self.max_candidates]
            match = self.candidates[-1]
        else:
            match.add(b, t_ns)
        if match.n < self.min_samples:
            return False
        if cur is None:
            self.current, self.candidates = match, []
            return False
        if not match.heartbeat_after_first or t_ns - max(cur.last_ns, match.first_ns) < self.quiet_s * 1e9:
            return False
        if cur.last_ns > match.first_ns:
            return False  # the established clock spoke after this one appeared: the old autopilot lives
        rebooted = match.boot_ns > cur.boot_ns + self.min_jump_s * 1e9
        self.current, self.candidates = match, []
        self.reboots += rebooted
        return rebooted


# MAV_RESULT values (common.xml; tests check them against pymavlink, which this module does not import)
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_UNSUPPORTED = 3
MAV_RESULT_IN_PROGRESS = 5
NO_ACK = -1  # RateOutcome.result when no COMMAND_ACK came within the timeout


@dataclass(frozen=True, slots=True)
class RateOutcome:
    """What became of one MAV_CMD_SET_MESSAGE_INTERVAL request."""

    name: str  # the message, e.g. "ATTITUDE"
    hz: float  # the rate asked for (<= 0: the message was to be switched off)
    result: int  # the COMMAND_ACK's MAV_RESULT, or NO_ACK
    retry_hz: float | None  # the rate asked for next instead (a refusal retried at a lower rate)
    was_retry: bool  # this request was itself the retry of a refused one


@dataclass
class RateRequests:
    """MAV_CMD_SET_MESSAGE_INTERVAL requests, one at a time, each matched with its COMMAND_ACK.

    ArduPilot's COMMAND_ACK names the command (511) but not the message it concerns
    (``result_param2`` is 0, no echo of param1), so only the order tells which request an ACK
    answers. Hence one request is outstanding at a time: the next leaves when the ACK of the
    previous one arrived, or ``ack_timeout_s`` after it was sent (then it is counted as
    unacknowledged; an ACK that arrives later still would be taken for the next request's, the
    one ambiguity left). ``MAV_RESULT_IN_PROGRESS`` is not an answer yet. A refusal (any other
    result but ACCEPTED) of a rate is retried once at ``retry_factor`` times that rate (ArduPilot
    refuses an interval shorter than 1.25 scheduler periods: 40 Hz is the most a Rover with its
    default 50 Hz SCHED_LOOP_RATE grants, so half of a refused rate is granted unless the rate
    was far off); UNSUPPORTED (the command itself is unknown) and refused switch-offs are not.
    Pure: the caller sends, receives and logs.
    """

    ack_timeout_s: float = 1.0
    retry_factor: float = 0.5
    accepted: int = 0
    refused: int = 0
    unacknowledged: int = 0
    granted: dict[str, float] = field(default_factory=dict)  # this round's accepted rates
    refusals: list[RateOutcome] = field(default_factory=list)  # this round's refusals and silences
    _queue: list[tuple[str, float, bool]] = field(default_factory=list)
    _outstanding: tuple[str, float, bool, int] | None = None  # (name, hz, was_retry, sent_ns)
    _round_open: bool = False

    def start(self, rates_hz: dict[str, float]) -> None:
        """A new round (the autopilot's first heartbeat, or a reboot): every rate again, in order."""
        self._queue = [(name, float(hz), False) for name, hz in rates_hz.items()]
        self._outstanding = None
        self.granted, self.refusals = {}, []
        self._round_open = True

    @property
    def busy(self) -> bool:
        """A request is outstanding or waiting to leave."""
        return self._outstanding is not None or bool(self._queue)

    def round_finished(self) -> bool:
        """True once when every request of the round has its outcome (to report the round)."""
        if self._round_open and not self.busy:
            self._round_open = False
            return True
        return False

    def next_request(self, now_ns: int) -> tuple[tuple[str, float] | None, RateOutcome | None]:
        """(the request to send now, as (name, hz), or None; the outcome of an outstanding
        request that just timed out, or None). The request returned is outstanding from now."""
        timed_out = None
        if self._outstanding is not None:
            name, hz, was_retry, sent_ns = self._outstanding
            if now_ns - sent_ns < self.ack_timeout_s * 1e9:
                return None, None
            self.unacknowledged += 1
            timed_out = RateOutcome(name, hz, NO_ACK, None, was_retry)
            self.refusals.append(timed_out)
            self._outstanding = None
        if not self._queue:
            return None, timed_out
        name, hz, was_retry = self._queue.pop(0)
        self._outstanding = (name, hz, was_retry, now_ns)
        return (name, hz), timed_out

    def on_ack(self, result: int) -> RateOutcome | None:
        """A COMMAND_ACK for MAV_CMD_SET_MESSAGE_INTERVAL: the outstanding request's outcome
        (None when nothing is outstanding, or while the autopilot says IN_PROGRESS)."""
        if self._outstanding is None or result == MAV_RESULT_IN_PROGRESS:
            return None
        name, hz, was_retry, _ = self._outstanding
        self._outstanding = None
        if result == MAV_RESULT_ACCEPTED:
            self.accepted += 1
            self.granted[name] = hz
            return RateOutcome(name, hz, result, None, was_retry)
        self.refused += 1
        retry_hz = None
        if not was_retry and hz > 0 and result != MAV_RESULT_UNSUPPORTED:
            retry_hz = hz * self.retry_factor
            self._queue.insert(0, (name, retry_hz, True))
        outcome = RateOutcome(name, hz, result, retry_hz, was_retry)
        self.refusals.append(outcome)
        return outcome
