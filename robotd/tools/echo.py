"""``robotd echo KEY``: print what a robotd publishes on a Zenoh key (one JSON line per sample).

``robotd/*/map`` without a wildcard queries the map once (the queryable), other keys subscribe.
"""

from __future__ import annotations

import json
import re
import sys
import threading
import time

import zenoh

from robotd.core.errors import DriverError
from robotd.formats.codec import decode_map

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"  # the daemon's default [zenoh] listen


def _client_config(connect: list[str]) -> zenoh.Config:
    conf = zenoh.Config()
    if connect:
        conf.insert_json5("mode", '"client"' if len(connect) == 1 else '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        conf.insert_json5("listen/endpoints", "[]")
    else:
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def _reason(exc: Exception) -> str:
    """Zenoh's message without the Rust source locations it appends (`` at /root/.cargo/…rs:447.``)
    and, for a config error, without the JSON5 wrapper around it."""
    text = str(exc)
    inner = re.search(r'msg: "(.*?)"', text)
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", inner.group(1) if inner else text).strip()


def open_session(connect: list[str]) -> zenoh.Session:
    """A Zenoh session to ``connect`` (the daemon's default endpoint when empty). Nothing listening
    there, or an endpoint Zenoh cannot parse, is a DriverError of one line saying what to change."""
    endpoints = connect or [DEFAULT_ENDPOINT]
    where = ", ".join(endpoints)
    try:
        conf = _client_config(endpoints)
    except zenoh.ZError as exc:
        raise DriverError(
            f"echo: --connect {where}: not a Zenoh endpoint ({_reason(exc)}); e.g. --connect {DEFAULT_ENDPOINT}"
        ) from None
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        if "Unable to connect" not in str(exc):
            raise DriverError(f"echo: cannot open a Zenoh session to {where}: {_reason(exc)}") from None
        raise DriverError(
            f"echo: nothing listens at {where}{'' if connect else ' (the default)'}: is robotd running there, "
            "with [zenoh] enabled? Point echo at it with --connect tcp/HOST:PORT, an endpoint of the daemon's "
            "[zenoh] listen"
        ) from None


def format_sample(key: str, payload: bytes) -> str:
    """A printable line for a published sample (CBOR maps summarised, JSON as is)."""
    if key.endswith("/map"):
        try:
            meta, lm = decode_map(payload)
            return json.dumps({"key": key, **{k: v for k, v in meta.items()}, "first_ids": lm.ids[:5].tolist()})
        except Exception as exc:
            return json.dumps({"key": key, "error": str(exc), "bytes": len(payload)})
    try:
        return json.dumps({"key": key, "value": json.loads(payload)})
    except ValueError:
        return json.dumps({"key": key, "bytes": len(payload)})


def echo(key: str, connect: list[str], count: int = 0, timeout_s: float = 0.0) -> int:
    """Print samples on ``key`` (one JSON line each). ``robotd/*/map`` queries the map once."""
    done = threading.Event()
    n = 0
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal n
        with lock:
            if done.is_set():
                return
            print(format_sample(str(sample.key_expr), sample.payload.to_bytes()), flush=True)
            n += 1
            if count and n >= count:
                done.set()

    with open_session(connect) as session:
        if key.endswith("/map") and "*" not in key:
            for reply in session.get(key, timeout=timeout_s or 5.0):
                if reply.ok is not None:
                    print(format_sample(str(reply.ok.key_expr), reply.ok.payload.to_bytes()), flush=True)
                    n += 1
            return 0 if n else 1
        sub = session.declare_subscriber(key, on_sample)
        t_end = time.monotonic() + timeout_s if timeout_s else float("inf")
        try:
            while not done.is_set() and time.monotonic() < t_end:
                done.wait(0.1)
        except KeyboardInterrupt:
            pass
        finally:
            done.set()
            sub.undeclare()
    sys.stdout.flush()
    return 0 if n or not count else 1
