"""A fleet on one Zenoh network: ``robotd fleet`` (the live rovers and their health) and ``robotd
router`` (a Zenoh router, for a base station or a host without zenohd).

Every robotd publishes under ``robotd/<robot.id>/`` and declares the liveliness token
``robotd/<id>/alive`` while it runs (robotd.outputs.zenoh), so a fleet needs no registry: the
rovers alive are the tokens alive. ``robotd fleet`` connects (``--connect``, default the local
``tcp/127.0.0.1:7447``; at a base station, its router), queries the tokens, listens to
``robotd/*/health`` and ``robotd/*/pose`` for ``--wait`` seconds and prints one row per live rover:
its health state and problems, frames per second, tracking, quality, landmarks, position and
latency. ``--watch`` then prints a line each time a rover joins or leaves (a token put or deleted:
a robotd that stops, crashes or drops off the network) with the table after it. docs/fleet.md.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from typing import Any

import zenoh

from robotd.core.errors import DriverError
from robotd.tools.echo import DEFAULT_ENDPOINT, open_session

ALIVE = "robotd/*/alive"
HEALTH = "robotd/*/health"
POSE = "robotd/*/pose"


def _robot(key: str) -> str:
    parts = key.split("/")
    return parts[1] if len(parts) >= 3 and parts[0] == "robotd" else key


def live_robots(session: zenoh.Session, timeout_s: float = 2.0) -> list[str]:
    """The robot ids whose liveliness token is alive, sorted."""
    ids: set[str] = set()
    for reply in session.liveliness().get(ALIVE, timeout=timeout_s):
        if reply.ok is not None:
            ids.add(_robot(str(reply.ok.key_expr)))
    return sorted(ids)


class FleetView:
    """The latest health and pose of every rover, from subscriptions on one session."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self._lock = threading.Lock()
        self.health: dict[str, dict[str, Any]] = {}
        self.pose: dict[str, dict[str, Any]] = {}
        self.seen: dict[str, float] = {}
        self._subs = [
            session.declare_subscriber(HEALTH, lambda s: self._on(s, self.health)),
            session.declare_subscriber(POSE, lambda s: self._on(s, self.pose)),
        ]

    def _on(self, sample: zenoh.Sample, into: dict[str, dict[str, Any]]) -> None:
        try:
            doc = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        rid = _robot(str(sample.key_expr))
        with self._lock:
            into[rid] = doc
            self.seen[rid] = time.monotonic()

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:
                pass

    def rows(self, alive: list[str]) -> list[dict[str, Any]]:
        with self._lock:
            health, pose = dict(self.health), dict(self.pose)
        rows = []
        for rid in alive:
            h, p = health.get(rid), pose.get(rid)
            up = (h or {}).get("uptime_s")
            done = (h or {}).get("frames_processed")
            rows.append(
                {
                    "robot": rid,
                    "state": (h or {}).get("state", "no health yet"),
                    "problems": (h or {}).get("problems", []),
                    "ready": (h or {}).get("ready"),
                    "fps": round(done / up, 1) if h and up and done is not None else None,
                    "tracking": (h or {}).get("tracking"),
                    "quality": (h or {}).get("quality"),
                    "landmarks": (h or {}).get("landmarks"),
                    "latency_p99_ms": ((h or {}).get("latency_ms") or {}).get("p99"),
                    "uptime_s": up,
                    "xyz_m": (p or {}).get("xyz_m"),
                    "robot_in_payload": (h or p or {}).get("robot"),
                }
            )
        return rows

    def wait_for_health(self, alive: list[str], wait_s: float) -> None:
        """Until every live rover has sent its health (1 Hz) and a pose, or ``wait_s`` passed."""
        t_end = time.monotonic() + wait_s
        while time.monotonic() < t_end:
            with self._lock:
                if all(r in self.health and r in self.pose for r in alive):
                    return
            time.sleep(0.05)


def _f(v: Any, fmt: str) -> str:
    return "–" if v is None else format(v, fmt)


def table(rows: list[dict[str, Any]], where: str) -> str:
    lines = [f"{len(rows)} rover{'s' if len(rows) != 1 else ''} alive at {where}", ""]
    if not rows:
        return "\n".join(lines)
    lines.append(
        "| robot | state | problems | fps | tracking | quality | landmarks | x y z m | latency p99 ms | up s |"
    )
    lines.append("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        xyz = " ".join(f"{v:+.2f}" for v in r["xyz_m"]) if r["xyz_m"] else "–"
        lines.append(
            f"| {r['robot']} | {r['state']} | {'; '.join(r['problems']) or '–'} | {_f(r['fps'], '.1f')} "
            f"| {'yes' if r['tracking'] else ('no' if r['tracking'] is not None else '–')} | {_f(r['quality'], 'd')} "
            f"| {_f(r['landmarks'], 'd')} | {xyz} | {_f(r['latency_p99_ms'], '.1f')} | {_f(r['uptime_s'], '.0f')} |"
        )
    return "\n".join(lines)


def fleet(
    connect: list[str], as_json: bool = False, wait_s: float = 2.0, watch: bool = False, timeout_s: float = 0.0
) -> int:
    """``robotd fleet`` (module docstring). 0 when at least one rover is alive, else 1."""
    where = ", ".join(connect or [DEFAULT_ENDPOINT])
    with open_session(connect) as session:
        view = FleetView(session)
        try:
            alive = live_robots(session)
            view.wait_for_health(alive, wait_s)
            rows = view.rows(alive)
            if as_json:
                print(json.dumps({"connect": where, "robots": rows}, sort_keys=True), flush=True)
            else:
                print(table(rows, where), flush=True)
            if watch:
                _watch(session, view, where, as_json, timeout_s)
            return 0 if rows else 1
        finally:
            view.close()


def _watch(session: zenoh.Session, view: FleetView, where: str, as_json: bool, timeout_s: float) -> None:
    """A line per rover joining or leaving, then the table, until Ctrl-C / SIGTERM or ``timeout_s``."""
    stop = threading.Event()
    changed = threading.Event()
    events: list[tuple[str, str]] = []
    lock = threading.Lock()

    def on_token(sample: zenoh.Sample) -> None:
        kind = "joined" if sample.kind == zenoh.SampleKind.PUT else "left"
        with lock:
            events.append((_robot(str(sample.key_expr)), kind))
        changed.set()

    sub = session.liveliness().declare_subscriber(ALIVE, on_token)
    old = (
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        if threading.current_thread() is threading.main_thread()
        else None
    )
    t_end = time.monotonic() + timeout_s if timeout_s else float("inf")
    try:
        while not stop.is_set() and time.monotonic() < t_end:
            if not changed.wait(0.2):
                continue
            changed.clear()
            with lock:
                batch, events[:] = list(events), []
            for rid, kind in batch:
                line = {"event": kind, "robot": rid, "t": time.time()}
                print(json.dumps(line) if as_json else f"{time.strftime('%H:%M:%S')} {rid} {kind}", flush=True)
            alive = live_robots(session)
            view.wait_for_health(alive, 1.5)
            rows = view.rows(alive)
            print(json.dumps({"connect": where, "robots": rows}) if as_json else table(rows, where), flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        sub.undeclare()
        if old is not None:
            signal.signal(signal.SIGTERM, old)
    sys.stdout.flush()


# --------------------------------------------------------------------------------------------
# a router


def router_config(listen: list[str], config_file: str | None = None) -> zenoh.Config:
    """A router's session config: the JSON5 file (config/zenoh-base-station.json5) or the endpoints."""
    if config_file:
        try:
            return zenoh.Config.from_file(config_file)
        except Exception as exc:
            raise DriverError(f"router: zenoh config {config_file}: {exc}") from None
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps(listen or [DEFAULT_ENDPOINT]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def run_router(listen: list[str], config_file: str | None = None, duration_s: float = 0.0) -> int:
    """``robotd router``: a Zenoh router until SIGINT / SIGTERM (or ``duration_s``)."""
    conf = router_config(listen, config_file)
    try:
        session = zenoh.open(conf)
    except Exception as exc:
        text = " ".join(str(exc).split())
        raise DriverError(
            f"router: cannot open the Zenoh router ({', '.join(listen) or config_file}): {text}"
        ) from None
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        locators = [str(x) for x in session.info.locators()] if hasattr(session.info, "locators") else []
        print(f"robotd router {session.info.zid()} listening on {', '.join(locators) or ', '.join(listen)}", flush=True)
        stop.wait(duration_s if duration_s > 0 else None)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        session.close()
    return 0
