"""Mutated recordings through the reader and the replay source (issue 15, item 5).

A small real recording (format 2, written by SessionWriter in several chunks) and a real format-1
one are damaged the ways the fault campaign found: bytes flipped, the file truncated, chunks
duplicated, record lengths and chunk sizes forged, PNG headers forged (with valid CRCs, so the
damage reaches the image decoder). Reading each through SessionReader and the ``mcap://`` replay
source must end normally or with robotd's own error type, within a time and memory bound.
"""

from __future__ import annotations

import base64
import resource
import struct
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import zstandard
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from drivers.dataset import McapCamera
from robotd.errors import RobotdError
from robotd.msgs import Odometry, PoseEstimate, StereoFrame
from robotd.record import SessionReader, SessionWriter
from robotd.stereo import RectifiedStereo

FORMAT1 = Path(__file__).resolve().parents[1] / "support" / "data" / "format1_sim_160x100.mcap"
MODEL = RectifiedStereo(60.0, 32.0, 20.0, 0.075, 64, 40)
MAGIC = b"\x89MCAP0\r\n"
PER_INPUT_S = 2.0  # a mutated input is read (twice) in well under this; the campaign saw 1–9.5 s
RSS_GROWTH_MB = 300  # the campaign saw 4 GB for one forged PNG header
EXAMPLES = 250  # per mutation kind; the whole file runs in ~20 s on the 2-core machine


def _recording(tmp: Path) -> bytes:
    rng = np.random.default_rng(7)
    path = tmp / "small.mcap"
    with SessionWriter(path, MODEL, {"source": "fuzz"}, chunk_size=6 * 1024) as w:
        for i in range(8):
            t = 1_000_000_000 + i * 33_333_333
            w.write_odometry(Odometry(t - 5, rng.normal(size=3), rng.normal(size=3), "sim", np.eye(6) * 0.01))
            img = (rng.integers(0, 40, (40, 64)) + np.arange(64) * 3).astype(np.uint8)
            w.write_frame(StereoFrame(t, i, img, np.roll(img, -3, axis=1), True, np.eye(4)))
            w.write_pose(PoseEstimate(t, rng.normal(size=3), rng.normal(size=3) * 0.1, np.eye(6), 50.0, 100))
    return path.read_bytes()


@pytest.fixture(scope="module")
def originals(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    return {"format2": _recording(tmp_path_factory.mktemp("fuzz")), "format1": FORMAT1.read_bytes()}


def records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of the top-level records of an intact file (MCAP framing)."""
    out, pos = [], len(MAGIC)
    while pos + 9 <= len(data) - len(MAGIC):
        op, n = struct.unpack_from("<BQ", data, pos)
        out.append((pos, op, n))
        pos += 9 + n
    return out


def chunks(data: bytes) -> list[tuple[int, int]]:
    return [(off, n) for off, op, n in records(data) if op == 0x06]


def _chunk_fields(data: bytes, off: int) -> tuple[int, int, str, int]:
    """(uncompressed-size field offset, crc field offset, compression, records offset)."""
    p = off + 9 + 16
    size_at, crc_at = p, p + 8
    (clen,) = struct.unpack_from("<I", data, p + 12)
    comp = data[p + 16 : p + 16 + clen].decode()
    return size_at, crc_at, comp, p + 16 + clen + 8


def rewrite_chunk(data: bytes, k: int, change) -> bytes:
    """Chunk k's records passed through ``change`` (bytes -> bytes), then recompressed with its
    sizes and CRC fixed: the framing stays valid, so the damage reaches the message decoders."""
    cs = chunks(data)
    off, n = cs[k % len(cs)]
    size_at, crc_at, comp, rec_at = _chunk_fields(data, off)
    (rlen,) = struct.unpack_from("<Q", data, rec_at - 8)
    body = data[rec_at : rec_at + rlen]
    raw = change(zstandard.decompress(body) if comp == "zstd" else body)
    new = zstandard.compress(raw) if comp == "zstd" else raw
    head = bytearray(data[off + 9 : rec_at - 8])
    struct.pack_into("<Q", head, size_at - off - 9, len(raw))
    struct.pack_into("<I", head, crc_at - off - 9, zlib.crc32(raw))
    rec = bytes(head) + struct.pack("<Q", len(new)) + new
    return data[:off] + struct.pack("<BQ", 0x06, len(rec)) + rec + data[off + 9 + n :]


def forge_png(data: bytes, k: int, width: int, height: int, depth: int) -> bytes:
    """The first PNG header in chunk k forged (IHDR width/height/bit depth) with a valid IHDR CRC
    and the chunk's CRC fixed, so only the image is wrong."""

    def forge(png: bytes) -> bytes:
        at = png.find(b"IHDR")
        if at < 0:
            return png
        ihdr = bytearray(png[at : at + 17])
        struct.pack_into(">IIB", ihdr, 4, width, height, depth)
        return png[:at] + bytes(ihdr) + struct.pack(">I", zlib.crc32(bytes(ihdr))) + png[at + 21 :]

    def change(raw: bytes) -> bytes:
        b64 = raw.find(b"iVBORw0KGgo")  # format 1: the PNG is base64 in JSON (same length after forging)
        if b64 >= 0 and (raw.find(b"IHDR") < 0 or b64 < raw.find(b"IHDR")):
            end = raw.index(b'"', b64)
            return raw[:b64] + base64.b64encode(forge(base64.b64decode(raw[b64:end]))) + raw[end:]
        return forge(raw)

    return rewrite_chunk(data, k, change)


def read_all(path: Path) -> None:
    """What replay does with a recording: SessionReader's events, then the mcap:// source."""
    t0 = time.monotonic()
    try:
        for _ in SessionReader(path).events():
            pass
    except RobotdError:
        pass
    try:
        with McapCamera(path) as cam:
            for _ in cam.frames():
                pass
            cam.recorded_odometry()
    except RobotdError:
        pass
    took = time.monotonic() - t0
    assert took < PER_INPUT_S, f"{took:.1f} s for one input"


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@pytest.fixture(scope="module", autouse=True)
def bounded_memory():
    before = _rss_mb()
    yield
    assert _rss_mb() - before < RSS_GROWTH_MB, f"peak RSS grew {_rss_mb() - before:.0f} MB while fuzzing"


FUZZ = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
# (where in the file or chunk as a fraction, xor mask)
FLIPS = st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=8)
WHICH = st.sampled_from(["format2", "format2", "format1"])  # the small one is cheaper: fuzzed more


@FUZZ
@given(which=WHICH, flips=FLIPS)
def test_flipped_bytes(originals, tmp_path: Path, which: str, flips: list[tuple[float, int]]) -> None:
    b = bytearray(originals[which])
    for where, xor in flips:
        b[int(where * len(b))] ^= xor
    p = tmp_path / "m.mcap"
    p.write_bytes(bytes(b))
    read_all(p)


@FUZZ
@given(which=WHICH, k=st.integers(0, 100), flips=FLIPS)
def test_flipped_bytes_behind_valid_crcs(originals, tmp_path: Path, which: str, k: int, flips) -> None:
    """Damage inside a chunk's messages (JSON, protobuf, PNG, base64) that its CRC does not catch:
    a writer may store no CRC, and the campaign's reader checked none."""

    def change(raw: bytes) -> bytes:
        b = bytearray(raw)
        for where, xor in flips:
            b[int(where * len(b))] ^= xor
        return bytes(b)

    p = tmp_path / "m.mcap"
    p.write_bytes(rewrite_chunk(originals[which], k, change))
    read_all(p)


@FUZZ
@given(which=WHICH, keep=st.floats(0, 1))
def test_truncated(originals, tmp_path: Path, which: str, keep: float) -> None:
    data = originals[which]
    p = tmp_path / "m.mcap"
    p.write_bytes(data[: int(keep * len(data))])
    read_all(p)


@FUZZ
@given(k=st.integers(0, 100), to=st.integers(0, 100))
def test_duplicated_chunks(originals, tmp_path: Path, k: int, to: int) -> None:
    data = originals["format2"]
    cs = chunks(data)
    off, n = cs[k % len(cs)]
    at = records(data)[to % len(records(data))][0]
    p = tmp_path / "m.mcap"
    p.write_bytes(data[:at] + data[off : off + 9 + n] + data[at:])
    read_all(p)


LENGTHS = st.one_of(st.sampled_from([0, 1, 8, 2**31, 2**32 - 1, 2**63, 2**64 - 1]), st.integers(0, 2**64 - 1))


@FUZZ
@given(which=WHICH, k=st.integers(0, 1000), length=LENGTHS, field=st.sampled_from(["record", "chunk-size"]))
def test_forged_lengths(originals, tmp_path: Path, which: str, k: int, length: int, field: str) -> None:
    """A record's length, or a chunk's stated uncompressed size (what a reader allocates)."""
    data = bytearray(originals[which])
    if field == "record":
        off = records(bytes(data))[k % len(records(bytes(data)))][0]
        struct.pack_into("<Q", data, off + 1, length)
    else:
        off, _ = chunks(bytes(data))[k % len(chunks(bytes(data)))]
        struct.pack_into("<Q", data, _chunk_fields(bytes(data), off)[0], length)
    p = tmp_path / "m.mcap"
    p.write_bytes(bytes(data))
    read_all(p)


SIDES = st.one_of(st.sampled_from([0, 1, 40, 64, 65535, 2**31 - 1, 2**32 - 1]), st.integers(0, 2**32 - 1))


@FUZZ
@given(which=WHICH, k=st.integers(0, 100), w=SIDES, h=SIDES, depth=st.sampled_from([1, 8, 16]))
@example(which="format2", k=3, w=30000, h=30000, depth=8)  # under OpenCV's own 2^30-pixel cap: 900 MB
def test_forged_png_headers(originals, tmp_path: Path, which: str, k: int, w: int, h: int, depth: int) -> None:
    p = tmp_path / "m.mcap"
    p.write_bytes(forge_png(originals[which], k, w, h, depth))
    read_all(p)


def test_a_forged_png_header_stops_the_read_there_and_says_so(originals, tmp_path: Path) -> None:
    """The campaign's 4 GB input: an image whose header claims 65535×65535, CRCs valid."""
    p = tmp_path / "m.mcap"
    p.write_bytes(forge_png(originals["format2"], 3, 65535, 65535, 8))  # chunk 3: frame 2
    r = SessionReader(p)
    n = sum(1 for _ in r.frames())
    assert 0 < n < 8 and r.stopped is not None
    assert "PNG header says 65535x65535" in r.stopped and "the recording's camera is 64x40" in r.stopped
