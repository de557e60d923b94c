"""A bounded, damage-tolerant sequential reader of MCAP files (the recordings' reading side).

``mcap``'s own readers trust the file: a record length or a chunk's uncompressed size is
allocated as stated (a forged field asks for gigabytes), a file without its summary (a recording
whose writer was killed) or with a torn last chunk yields nothing or an exception from deep
inside, and a file missing its last 100 bytes gives 0 messages. This reader walks the records
from the start of the file, in file order, and

- never allocates more than the file holds or the stated limits allow: a top-level record is at
  most ``max_record_bytes``, a chunk decompresses to at most ``max_chunk_bytes`` (checked against
  its header before decompressing, and again while decompressing), a message is at most
  ``max_message_bytes``;
- checks each chunk's CRC of its uncompressed records when the writer stored one;
- stops at the first damage (a truncated or forged record, a CRC mismatch, an unknown
  compression) and says where: :attr:`McapScan.stopped` is one line, byte offset, record and
  reason; everything before it was read;
- says whether the file was closed cleanly (its DataEnd and Footer were reached):
  :attr:`McapScan.finished`.

Record layouts are the MCAP specification's (opcode u8, length u64, little-endian fields;
strings and byte arrays prefixed by a u32 length, maps by a u32 byte length). Only what robotd
needs is parsed: Header, Schema, Channel, Message, Chunk, Metadata, DataEnd, Footer and the
summary's Statistics; index records are skipped.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_STATISTICS, OP_METADATA, OP_DATA_END = 0x0B, 0x0C, 0x0F
_NAMES = {
    0x01: "Header", 0x02: "Footer", 0x03: "Schema", 0x04: "Channel", 0x05: "Message", 0x06: "Chunk",
    0x07: "MessageIndex", 0x08: "ChunkIndex", 0x09: "Attachment", 0x0A: "AttachmentIndex",
    0x0B: "Statistics", 0x0C: "Metadata", 0x0D: "MetadataIndex", 0x0E: "SummaryOffset", 0x0F: "DataEnd",
}  # fmt: skip

# Limits. A robotd chunk is ~4 MiB (SessionWriter.chunk_size) and its largest message an image
# (a 4096×4096 mono8 RawImage is 16 MiB); the limits leave room for that and no more.
MAX_RECORD_BYTES = 96 * 1024 * 1024
MAX_CHUNK_BYTES = 96 * 1024 * 1024
MAX_MESSAGE_BYTES = 32 * 1024 * 1024
MAX_SCHEMA_BYTES = 1024 * 1024
MAX_SUMMARY_BYTES = 16 * 1024 * 1024


class Damage(ValueError):
    """A record that cannot be what it says it is (internal: the scan stops there)."""


@dataclass(frozen=True, slots=True)
class SchemaRec:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True, slots=True)
class ChannelRec:
    id: int
    schema_id: int
    topic: str
    message_encoding: str


@dataclass(frozen=True, slots=True)
class MessageRec:
    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes
    offset: int  # byte offset of the record that holds it (the message, or its chunk)


@dataclass(slots=True)
class Summary:
    """What a cleanly closed file's summary says (None fields: absent)."""

    channels: dict[int, ChannelRec] = field(default_factory=dict)
    message_counts: dict[int, int] | None = None


class _Body:
    """Bounds-checked little-endian reads over one record body."""

    __slots__ = ("buf", "pos")

    def __init__(self, buf: bytes) -> None:
        self.buf = buf
        self.pos = 0

    def take(self, n: int, what: str) -> bytes:
        if n < 0 or self.pos + n > len(self.buf):
            raise Damage(f"{what} needs {n} bytes, {len(self.buf) - self.pos} left in the record")
        b = self.buf[self.pos : self.pos + n]
        self.pos += n
        return b

    def u16(self, what: str) -> int:
        return int(struct.unpack("<H", self.take(2, what))[0])

    def u32(self, what: str) -> int:
        return int(struct.unpack("<I", self.take(4, what))[0])

    def u64(self, what: str) -> int:
        return int(struct.unpack("<Q", self.take(8, what))[0])

    def string(self, what: str) -> str:
        raw = self.take(self.u32(what), what)
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise Damage(f"{what} is not UTF-8") from None

    def bytes_(self, what: str, length_bytes: int = 4) -> bytes:
        n = self.u32(what) if length_bytes == 4 else self.u64(what)
        return self.take(n, what)

    def string_map(self, what: str) -> dict[str, str]:
        end = self.u32(what) + self.pos
        if end > len(self.buf):
            raise Damage(f"{what} map runs past its record")
        out: dict[str, str] = {}
        while self.pos < end:
            k = self.string(what)
            out[k] = self.string(what)
        if self.pos != end:
            raise Damage(f"{what} map overruns its stated length")
        return out

    def rest(self) -> bytes:
        b = self.buf[self.pos :]
        self.pos = len(self.buf)
        return b


def _decompress(compression: str, data: bytes, size: int, limit: int) -> bytes:
    """A chunk's records, at most ``limit`` bytes whatever its header or stream claim."""
    if size > limit:
        raise Damage(f"chunk claims {size} uncompressed bytes, limit {limit}")
    if compression == "":
        out = data
    elif compression == "zstd":
        import zstandard

        try:
            # a forged frame header cannot ask for a window larger than robotd's writer ever uses
            dctx = zstandard.ZstdDecompressor(max_window_size=1 << 25)
            parts: list[bytes] = []
            got = 0
            with dctx.stream_reader(io.BytesIO(data)) as r:
                # in pieces, so memory follows what the stream really holds, not what the header
                # claims; one byte more than stated shows a forged size
                while got <= size and (piece := r.read(min(1 << 20, size + 1 - got))):
                    parts.append(piece)
                    got += len(piece)
            out = b"".join(parts)
        except zstandard.ZstdError as exc:
            raise Damage(f"zstd: {exc}") from None
    else:
        raise Damage(f"chunk compression {compression!r} is not one robotd writes (zstd or none)")
    if len(out) != size:
        raise Damage(f"chunk decompresses to {'more than' if len(out) > size else len(out)} bytes, header says {size}")
    return out


class McapScan:
    """Read ``path`` sequentially; see the module docstring. Not thread-safe.

    ``preamble()`` reads the records before the first chunk or message (the header, schemas,
    channels and metadata a robotd recording writes first); ``messages()`` then walks the whole
    data section in file order. After a walk, ``stopped`` says where and why it ended early
    (None: it reached the end of the data), ``finished`` whether the file was closed cleanly.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        max_record_bytes: int = MAX_RECORD_BYTES,
        max_chunk_bytes: int = MAX_CHUNK_BYTES,
        max_message_bytes: int = MAX_MESSAGE_BYTES,
    ) -> None:
        self.path = Path(path)
        self.size = os.path.getsize(self.path)
        self.max_record_bytes = max_record_bytes
        self.max_chunk_bytes = max_chunk_bytes
        self.max_message_bytes = max_message_bytes
        self.header: tuple[str, str] | None = None  # (profile, library)
        self.schemas: dict[int, SchemaRec] = {}
        self.channels: dict[int, ChannelRec] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.stopped: str | None = None
        self.finished = False
        self.position = 0  # bytes read up to the last whole record

    # ------------------------------------------------------------------ walking
    def preamble(self) -> None:
        """Header, schemas, channels and metadata up to the first chunk or message."""
        for _ in self._walk(until_data=True):
            pass

    def messages(self) -> Iterator[tuple[ChannelRec, MessageRec]]:
        """Every message in file order, with its channel; stops at the first damage."""
        yield from self._walk(until_data=False)

    def _fail(self, offset: int, reason: str) -> None:
        self.stopped = f"stopped at byte {offset} of {self.size}: {reason}"

    def _walk(self, until_data: bool) -> Iterator[tuple[ChannelRec, MessageRec]]:
        self.stopped, self.finished, self.position = None, False, 0
        with open(self.path, "rb") as f:
            magic = f.read(len(MAGIC))
            if magic != MAGIC:
                self._fail(0, "not an MCAP file (no MCAP magic at its start)")
                return
            offset = len(MAGIC)
            self.position = offset
            while True:
                head = f.read(9)
                if not head:
                    self._fail(offset, "the file ends without its DataEnd/Footer (not closed cleanly)")
                    return
                if len(head) < 9:
                    self._fail(offset, f"a record header of {len(head)} of 9 bytes (truncated)")
                    return
                op, length = struct.unpack("<BQ", head)
                name = _NAMES.get(op, f"opcode 0x{op:02x}")
                left = self.size - offset - 9
                if length > left:
                    self._fail(offset, f"{name} record of {length} bytes, only {left} left in the file (truncated)")
                    return
                if length > self.max_record_bytes:
                    self._fail(offset, f"{name} record of {length} bytes, limit {self.max_record_bytes}")
                    return
                if until_data and op in (OP_CHUNK, OP_MESSAGE):
                    return
                body = f.read(length)
                if len(body) != length:
                    self._fail(offset, f"{name} record: read {len(body)} of {length} bytes")
                    return
                try:
                    if op == OP_CHUNK:
                        yield from self._chunk(_Body(body), offset)
                    elif op == OP_DATA_END:
                        self.finished = self._check_end(f, offset + 9 + length)
                        self.position = self.size if self.finished else offset + 9 + length
                        if not self.finished:
                            self._fail(offset + 9 + length, "all data read; the summary after it is damaged")
                        return
                    else:
                        msg = self._record(op, _Body(body), offset)
                        if msg is not None:
                            yield msg
                except Damage as exc:
                    self._fail(offset, f"{name} record: {exc}")
                    return
                offset += 9 + length
                self.position = offset

    def _check_end(self, f: io.BufferedReader, data_end: int) -> bool:
        """After DataEnd: the file ends with a Footer record and the magic (its summary is not read)."""
        tail = 9 + 20 + len(MAGIC)
        if self.size - data_end < tail:
            return False
        f.seek(self.size - tail)
        b = f.read(tail)
        return b[:1] == bytes([OP_FOOTER]) and struct.unpack("<Q", b[1:9])[0] == 20 and b[-8:] == MAGIC

    def _record(self, op: int, b: _Body, offset: int) -> tuple[ChannelRec, MessageRec] | None:
        if op == OP_HEADER:
            self.header = (b.string("profile"), b.string("library"))
        elif op == OP_SCHEMA:
            sid, name, enc = b.u16("schema id"), b.string("schema name"), b.string("schema encoding")
            data = b.bytes_("schema data")
            if len(data) > MAX_SCHEMA_BYTES:
                raise Damage(f"schema {name!r} of {len(data)} bytes, limit {MAX_SCHEMA_BYTES}")
            self.schemas[sid] = SchemaRec(sid, name, enc, data)
        elif op == OP_CHANNEL:
            cid, sid = b.u16("channel id"), b.u16("channel schema id")
            topic, enc = b.string("channel topic"), b.string("channel message encoding")
            b.string_map("channel metadata")
            if sid and sid not in self.schemas:
                raise Damage(f"channel {topic!r} refers to schema {sid}, not defined before it")
            self.channels[cid] = ChannelRec(cid, sid, topic, enc)
        elif op == OP_MESSAGE:
            cid, seq, log_t, pub_t = b.u16("channel id"), b.u32("sequence"), b.u64("log time"), b.u64("publish time")
            data = b.rest()
            if len(data) > self.max_message_bytes:
                raise Damage(f"message of {len(data)} bytes, limit {self.max_message_bytes}")
            ch = self.channels.get(cid)
            if ch is None:
                raise Damage(f"message on channel {cid}, not defined before it")
            return ch, MessageRec(cid, seq, log_t, pub_t, data, offset)
        elif op == OP_METADATA:
            name = b.string("metadata name")
            self.metadata[name] = b.string_map("metadata")
        elif op == OP_FOOTER:
            raise Damage("a Footer inside the data section")
        # other records (indexes, attachments, statistics) carry nothing robotd reads here
        return None

    def _chunk(self, b: _Body, offset: int) -> Iterator[tuple[ChannelRec, MessageRec]]:
        b.u64("chunk start time"), b.u64("chunk end time")
        size, crc = b.u64("chunk uncompressed size"), b.u32("chunk crc")
        compression = b.string("chunk compression")
        data = b.bytes_("chunk records", length_bytes=8)
        records = _decompress(compression, data, size, self.max_chunk_bytes)
        if crc and zlib.crc32(records) != crc:
            raise Damage(f"chunk CRC mismatch (stored {crc:08x}, computed {zlib.crc32(records):08x})")
        inner = _Body(records)
        while inner.pos < len(records):
            op = inner.take(1, "chunk record opcode")[0]
            body = inner.take(inner.u64("chunk record length"), f"chunk {_NAMES.get(op, hex(op))} record")
            if op not in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
                raise Damage(f"a {_NAMES.get(op, f'opcode 0x{op:02x}')} record inside a chunk")
            msg = self._record(op, _Body(body), offset)
            if msg is not None:
                yield msg

    # ------------------------------------------------------------------ summary
    def summary(self) -> Summary | None:
        """The channels and per-channel message counts from a cleanly closed file's summary
        (None when the file has no readable summary). Bounded like the data section."""
        tail = 9 + 20 + len(MAGIC)
        if self.size < len(MAGIC) + tail:
            return None
        with open(self.path, "rb") as f:
            f.seek(self.size - tail)
            t = f.read(tail)
            if t[:1] != bytes([OP_FOOTER]) or t[-8:] != MAGIC:
                return None
            start = struct.unpack("<Q", t[9:17])[0]
            end = self.size - tail
            if start == 0 or not len(MAGIC) <= start <= end or end - start > MAX_SUMMARY_BYTES:
                return None
            f.seek(start)
            body = _Body(f.read(end - start))
        out = Summary()
        try:
            while body.pos < len(body.buf):
                op = body.take(1, "summary opcode")[0]
                rec = _Body(body.take(body.u64("summary record length"), "summary record"))
                if op == OP_CHANNEL:
                    cid, sid = rec.u16("channel id"), rec.u16("schema id")
                    out.channels[cid] = ChannelRec(cid, sid, rec.string("topic"), rec.string("encoding"))
                elif op == OP_STATISTICS:
                    for what in ("messages", "schemas(2)", "channels", "attachments", "metadata", "chunks"):
                        rec.take(8 if what == "messages" else 2 if what == "schemas(2)" else 4, what)
                    rec.u64("start"), rec.u64("end")
                    n = rec.u32("channel message counts")
                    if n % 10 or rec.pos + n > len(rec.buf):
                        raise Damage("channel message counts")
                    counts = {}
                    for _ in range(n // 10):
                        cid = rec.u16("channel")
                        counts[cid] = rec.u64("count")
                    out.message_counts = counts
        except Damage:
            return None
        return out
