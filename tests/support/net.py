"""Loopback networking for the tests: a free TCP port and a Zenoh client configuration."""

from __future__ import annotations

import json
import socket
from typing import Any


def free_port() -> int:
    """A TCP port on 127.0.0.1 nobody listens on right now (the OS picks it)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def zenoh_client(port: int) -> Any:
    """A Zenoh client configuration connecting to tcp/127.0.0.1:``port``, without multicast scouting."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf
