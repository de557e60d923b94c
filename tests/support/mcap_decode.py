"""Decode a recording the way another tool would: the ``mcap`` library's reader and the schemas
the file itself declares (never robotd's own decoders)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mcap.reader import make_reader


def decode_all(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """Every message of ``path`` through the ``mcap`` library's own reader (CRCs checked), decoded
    with the schema the file declares for its channel: protobuf classes built from the file's
    FileDescriptorSet (not robotd's), JSON parsed. topic -> [(log_time, message)]."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    out: dict[str, list[tuple[int, Any]]] = {}
    classes: dict[int, Any] = {}
    with open(path, "rb") as f:
        r = make_reader(f, validate_crcs=True)
        for schema, channel, message in r.iter_messages(log_time_order=False):
            assert schema is not None, channel.topic
            if channel.message_encoding == "protobuf":
                assert schema.encoding == "protobuf"
                if schema.id not in classes:
                    pool = descriptor_pool.DescriptorPool()
                    for fd in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                        pool.Add(fd)
                    classes[schema.id] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
                msg = classes[schema.id].FromString(message.data)
            else:
                assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
                props = json.loads(schema.data)["properties"]
                msg = json.loads(message.data)
                assert set(msg) <= set(props), (channel.topic, set(msg) - set(props))
            out.setdefault(channel.topic, []).append((message.log_time, msg))
    return out
