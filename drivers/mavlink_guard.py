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
