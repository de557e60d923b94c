"""What ``robotd replay-many`` replays, and each source's digest.

A source argument is one of:

- a URL of a camera that is not hardware (the registered cameras, drivers.cameras: the simulated
  rover, whose query names the world, the seed, the length; a dataset folder; a recording); a glob
  in a folder's or file's path gives one source per match;
- a path or a glob (``archive/**/*.mcap``): a file with a recording's suffix is a recording, a
  folder a camera driver claims (a KITTI or an EuRoC sequence: ``claims_folder``) that driver's
  URL, any other folder the recordings directly in it.

Which is which is what each camera driver declares (``reads``: a folder, a file, or nothing: the
URL is the source), never its scheme.

Paths become absolute, so a Ray worker on another machine reads the same path (it must see it:
docs/fleet.md, "Ray").

The digest names a source's content, so results are reused across runs (and across machines that
see the data under other paths) exactly when the data are the same:

- a simulated source (its URL reads nothing): the URL's scheme, world and query, sorted (the world
  is code, and the code's version is in the result's key besides);
- a recording: the SHA-256 of the file (exact). Hashing a 10 GB file takes a while, so the digest
  is cached by (path, size, mtime, inode) in the results folder: a rerun reads no recording twice;
- a dataset folder: every file's relative path, size and mtime, plus the SHA-256 of its small
  text files (``calib.txt``, ``times.txt``, ``poses.txt``, ``data.csv``, ``sensor.yaml``,
  ``SHA256SUMS``, …). Cheap (one ``stat`` per image); an image rewritten in place with the same
  size and mtime would not be noticed (``--rerun`` runs everything again).

The URL's query (``start``, ``stop``, ``stride``, ``drop``, …) is part of every digest.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

from drivers.cameras import Registration, cameras, loaded, path_scheme, scheme_of, suffixes
from robotd.core.errors import DriverError, InputError

# small files of a dataset folder whose content goes into its digest (the index, the calibration,
# the truth); images are named, sized and dated only
INDEX_SUFFIXES = (".txt", ".csv", ".yaml", ".yml", ".json")
INDEX_NAMES = ("SHA256SUMS",)
INDEX_MAX_BYTES = 8 << 20
_CHUNK = 1 << 20


@dataclass(frozen=True)
class Source:
    """One replay source: ``url`` is what ``robotd replay`` takes; ``name`` is for the table."""

    url: str
    name: str

    @property
    def scheme(self) -> str:
        return source_scheme(self.url)


def source_scheme(url: str) -> str:
    if "://" in url:
        return url.partition("://")[0]
    return path_scheme(url) or ""


def _replayable() -> dict[str, Registration]:
    """scheme -> registration of every camera that is not hardware (what replay-many replays)."""
    return {r.scheme: r for r in cameras(hardware=False)}


def _reads(url: str) -> str | None:
    """What ``url``'s camera reads (drivers.cameras.READS), None when it is no replayable camera's."""
    try:
        reg = _replayable().get(scheme_of(url))
    except DriverError:
        return None
    return None if reg is None else reg.kind.reads


def _reads_nothing(url: str) -> bool:
    """The URL is the whole source (a simulated world), no file or folder."""
    return _reads(url) == "nothing"


def _has_magic(text: str) -> bool:
    return glob.has_magic(text)


def _name(url: str) -> str:
    """A short name for the table: the file or folder name (with the query), or the URL of a source
    that reads nothing (a simulated world)."""
    if _reads_nothing(url):
        return url
    rest = url.partition("://")[2] if "://" in url else url
    path, _, query = rest.partition("?")
    base = Path(path).name or path
    return f"{base}?{query}" if query else base


def _classify(path: Path, where: str) -> list[str]:
    """A path -> source URLs (a recording, a dataset folder, or a folder's recordings)."""
    p = path.resolve()
    recording = suffixes()
    if p.is_file():
        if recording and p.name.endswith(recording):
            return [str(p)]
        raise InputError(f"{where}: {path} is not a recording ({', '.join(recording)})")
    if p.is_dir():
        folders = [r for r in _replayable().values() if r.kind.reads == "folder"]
        for reg in folders:
            driver = loaded(reg)
            if driver is not None and driver.claims_folder(p):
                return [f"{reg.scheme}://{p}"]
        recs = sorted(str(f) for f in p.iterdir() if f.is_file() and recording and f.name.endswith(recording))
        if recs:
            return recs
        kinds = ", ".join(r.kind.folder or f"a {r.scheme}:// folder" for r in folders)
        recordings = f"{recording[0]} recordings" if recording else "recordings"
        raise InputError(f"{where}: {path} is neither {kinds} nor a folder of {recordings}")
    raise InputError(f"{where}: {path} does not exist")


def _expand_url(item: str) -> list[str]:
    scheme, _, rest = item.partition("://")
    known = _replayable()
    if scheme not in known:
        raise InputError(f"source {item!r}: unknown scheme {scheme!r}; known: {', '.join(known)}")
    if known[scheme].kind.reads == "nothing":
        return [item]
    path, sep, query = rest.partition("?")
    if _has_magic(path):
        matches = sorted(glob.glob(path, recursive=True))
        if not matches:
            raise InputError(f"source {item!r}: no path matches {path!r}")
    else:
        matches = [path]
    return [f"{scheme}://{Path(m).resolve() if m else m}{sep}{query}" for m in matches]


def expand_sources(items: Iterable[str], lists: Sequence[str | Path] = ()) -> list[Source]:
    """The sources named by ``items`` (URLs, paths, globs) and by the files ``lists`` (one item a
    line; blank lines and ``#`` comments skipped), in order, each once. InputError names the item
    that names nothing."""
    all_items = list(items)
    for f in lists:
        try:
            lines = Path(f).read_text(encoding="utf-8").splitlines()
        except OSError as exc:
            raise InputError(f"--sources-file {f}: {exc.strerror or exc}") from None
        all_items += [ln.strip() for ln in lines if ln.strip() and not ln.strip().startswith("#")]
    urls: list[str] = []
    for item in all_items:
        if "://" in item:
            urls += _expand_url(item)
        elif _has_magic(item):
            matches = sorted(glob.glob(item, recursive=True))
            if not matches:
                raise InputError(f"source {item!r}: no file or folder matches")
            for m in matches:
                urls += _classify(Path(m), f"source {item!r}")
        else:
            urls += _classify(Path(item), f"source {item!r}")
    seen: set[str] = set()
    out: list[Source] = []
    for u in urls:
        if u not in seen:
            seen.add(u)
            out.append(Source(u, _name(u)))
    if not out:
        raise InputError("replay-many: no source given")
    return out


def check_sources(sources: Sequence[Source]) -> None:
    """Each source's URL as its driver's parser judges it (scheme and parameters; nothing opened),
    so a typo is one error line before any work starts."""
    import drivers
    from robotd.core.errors import DriverError

    for s in sources:
        try:
            drivers.check_camera_url(s.url)
        except DriverError as exc:
            raise InputError(f"source {s.url}: {exc}") from None


# --------------------------------------------------------------------------------------------
# digests


def _canonical_query(query: str) -> str:
    return "&".join(f"{k}={v}" for k, v in sorted(parse_qsl(query, keep_blank_values=True)))


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


class DigestCache:
    """Digests of recordings by (path, size, mtime_ns, inode), kept in a JSON file (thread-safe)."""

    def __init__(self, path: Path | None = None) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._data: dict[str, list[object]] = {}
        self.hashed = 0  # files read in full this run
        if path is not None and path.is_file():
            try:
                self._data = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                self._data = {}

    def file_digest(self, path: Path) -> str:
        st = path.stat()
        stamp = [st.st_size, st.st_mtime_ns, st.st_ino]
        key = str(path)
        with self._lock:
            hit = self._data.get(key)
        if hit is not None and hit[:3] == stamp:
            return str(hit[3])
        digest = file_sha256(path)
        with self._lock:
            self._data[key] = [*stamp, digest]
            self.hashed += 1
        return digest

    def save(self) -> None:
        if self.path is None:
            return
        with self._lock:
            text = json.dumps(self._data, sort_keys=True)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, self.path)


def folder_digest(root: Path) -> str:
    """Every file's relative path, size and mtime, and the content of the small index files."""
    h = hashlib.sha256()
    files = sorted(p for p in root.rglob("*") if p.is_file())
    for p in files:
        st = p.stat()
        rel = p.relative_to(root).as_posix()
        h.update(f"{rel}\t{st.st_size}\t{st.st_mtime_ns}\n".encode())
        if (p.suffix.lower() in INDEX_SUFFIXES or p.name in INDEX_NAMES) and st.st_size <= INDEX_MAX_BYTES:
            h.update(file_sha256(p).encode() + b"\n")
    h.update(f"{len(files)} files\n".encode())
    return h.hexdigest()


def source_digest(url: str, cache: DigestCache | None = None) -> str:
    """The digest of a source's content and selection (module docstring); 32 hex digits."""
    scheme = source_scheme(url)
    reads = _reads(url)
    if reads == "nothing":
        parts = urlsplit(url)
        content = f"world={parts.netloc}"
        query = parts.query
    else:
        rest = url.partition("://")[2] if "://" in url else url
        path_text, _, query = rest.partition("?")
        path = Path(path_text)
        if path.is_file():
            content = "sha256=" + (cache.file_digest(path) if cache is not None else file_sha256(path))
        elif path.is_dir():
            content = "folder=" + folder_digest(path)
        else:
            raise InputError(f"source {url}: {path} does not exist")
        if reads == "file":
            scheme = "recording"
    h = hashlib.sha256(f"{scheme}\n{_canonical_query(query)}\n{content}\n".encode())
    return h.hexdigest()[:32]
