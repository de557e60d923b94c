"""Under systemd, every line robotd writes to the journal carries its syslog priority.

journald reads a ``<N>`` prefix at the start of each line of a service's stdout and stderr
(``SyslogLevelPrefix=``, on by default) as the line's priority, so ``journalctl -p err -u robotd``
shows the errors alone. robotd's log lines had it (:class:`JournalFormatter`); the rest did not:
the one-line ``robotd: error: …`` of a bad config, argparse's usage and error, Python warnings,
tracebacks (each continuation line is a journal line of its own), and what native libraries
(depthai, OpenCV, the Zenoh and Foxglove runtimes) print on the file descriptors themselves. So
:func:`install`, which the ``robotd`` command calls first when its stderr is the journal:

- replaces ``sys.stderr`` (and ``sys.stdout`` when it is the journal too) by a stream that starts
  each line with the priority of what is being written: :func:`priority` sets it for a block (the
  error handler 3, argparse's errors 3, warnings 4, tracebacks 3), a line that carries its own
  prefix (a log line) keeps it, anything else gets the stream's default (stderr 4, stdout 6);
- hooks ``sys.excepthook``, ``threading.excepthook``, ``sys.unraisablehook`` and
  ``warnings.showwarning`` to write at their priority;
- points file descriptors 2 (and 1) at a pipe read by a small relay process, which gives each
  unprefixed line (a native library's) the priority its level tag says (``[warning]``,
  ``[ WARN:0@…]``, `` ERROR ``, …; ``Fatal Python error`` and what follows it: 2) and passes
  prefixed lines through. It is a process, not a thread, so a crash's last words still reach the
  journal; it ignores SIGTERM and SIGINT and ends when robotd's end closes the pipe.

"The journal" is what systemd says it is: ``$JOURNAL_STREAM`` holds the device and inode of the
stream it connected, and the descriptor must still be that stream (systemd.exec(5)); a robotd
started from a service with its stderr redirected elsewhere writes plain lines there.
"""

from __future__ import annotations

import atexit
import contextlib
import io
import logging
import os
import re
import selectors
import signal
import sys
import threading
import warnings
from collections.abc import Iterator
from typing import Any, TextIO

# syslog priorities (RFC 5424) of the logging levels, for journald's "<N>" line prefix
SYSLOG_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}
CRIT, ERR, WARNING, INFO = 2, 3, 4, 6
STDERR_DEFAULT = WARNING  # a line on stderr nobody marked: a diagnostic, not an error
STDOUT_DEFAULT = INFO

_PREFIXED = re.compile(r"<[0-7]>")
_PREFIXED_B = re.compile(rb"<[0-7]>")


class JournalFormatter(logging.Formatter):
    """Prefixes each line of a record with ``<N>``, its syslog priority, the continuation lines of
    a multi-line message or traceback too (journald takes each line as an entry of its own).
    journald stamps the time itself."""

    def format(self, record: logging.LogRecord) -> str:
        prio = SYSLOG_PRIORITY.get(record.levelno, INFO if record.levelno < logging.WARNING else ERR)
        return "\n".join(f"<{prio}>{line}" for line in super().format(record).split("\n"))


def connected(fd: int) -> bool:
    """Whether ``fd`` is the journal stream systemd connected ($JOURNAL_STREAM = "DEVICE:INODE")."""
    dev, sep, ino = os.environ.get("JOURNAL_STREAM", "").partition(":")
    if not sep:
        return False
    try:
        st = os.fstat(fd)
        return (st.st_dev, st.st_ino) == (int(dev), int(ino))
    except (OSError, ValueError):
        return False


_installed = False
_local = threading.local()


def active() -> bool:
    """Lines on stderr should carry a priority: :func:`install` ran, or stderr is the journal."""
    return _installed or connected(2)


def current_priority(default: int) -> int:
    return int(getattr(_local, "priority", default))


@contextlib.contextmanager
def priority(prio: int) -> Iterator[None]:
    """Lines this thread starts on a :class:`PriorityStream` inside the block get priority ``prio``."""
    before = getattr(_local, "priority", None)
    _local.priority = prio
    try:
        yield
    finally:
        if before is None:
            del _local.priority
        else:
            _local.priority = before


class PriorityStream(io.TextIOBase):
    """A text stream that writes each line to ``stream`` with a ``<N>`` prefix: the one it carries
    already, else the priority of the thread that started the line (:func:`priority`), else
    ``default``. A partial line waits for its end (or :meth:`close`)."""

    def __init__(self, stream: TextIO, default: int) -> None:
        self._stream = stream
        self._default = default
        self._lock = threading.RLock()
        self._partial = ""
        self._prio = default

    def write(self, s: str) -> int:
        with self._lock:
            *lines, rest = s.split("\n")
            out = []
            for piece in lines:
                if not self._partial:
                    self._prio = current_priority(self._default)
                out.append(self._prefixed(self._partial + piece))
                self._partial = ""
            if rest:
                if not self._partial:
                    self._prio = current_priority(self._default)
                self._partial += rest
            if out:
                self._stream.write("".join(out))
        return len(s)

    def _prefixed(self, line: str) -> str:
        return f"{line}\n" if _PREFIXED.match(line) else f"<{self._prio}>{line}\n"

    def flush(self) -> None:
        self._stream.flush()

    def close(self) -> None:
        """Writes out a partial line (at exit); the underlying stream stays open."""
        with self._lock:
            if self._partial:
                self._stream.write(self._prefixed(self._partial))
                self._partial = ""
        self._stream.flush()

    def writable(self) -> bool:
        return True

    def fileno(self) -> int:
        return self._stream.fileno()

    def isatty(self) -> bool:
        return self._stream.isatty()

    @property
    def encoding(self) -> str:  # type: ignore[override]
        return self._stream.encoding

    @property
    def errors(self) -> str | None:  # type: ignore[override]
        return self._stream.errors

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


# ----------------------------------------------------------------------------------------------
# the native relay

_TAG_PRIORITY = {
    b"critical": CRIT, b"fatal": CRIT, b"error": ERR, b"err": ERR, b"warning": WARNING, b"warn": WARNING,
    b"info": INFO, b"debug": 7, b"trace": 7, b"verbose": 7,
}  # fmt: skip
# spdlog (depthai) "[…] [warning] …", OpenCV "[ WARN:0@0.1] …", Rust tracing (Zenoh) "2024-…Z  WARN …"
_TAGS = (
    re.compile(rb"\[(critical|error|err|warning|warn|info|debug|trace)\]", re.IGNORECASE),
    re.compile(rb"^\[\s*(FATAL|ERROR|WARN|INFO|DEBUG|VERBOSE)[:\]]"),
    re.compile(rb"^\S*\s+(ERROR|WARN|INFO|DEBUG|TRACE)\s"),
)
_WORDS = ((re.compile(rb"\berror\b", re.IGNORECASE), ERR), (re.compile(rb"\bwarn(ing)?\b", re.IGNORECASE), WARNING))


def native_priority(line: bytes, default: int) -> int:
    """The priority of a line a library printed itself: its level tag, else the word error or
    warning in it, else ``default``."""
    for rx in _TAGS:
        m = rx.search(line)
        if m:
            return _TAG_PRIORITY[m.group(1).lower()]
    for rx, prio in _WORDS:
        if rx.search(line):
            return prio
    return default


class _Relay:
    """What the relay process does with one pipe: whole lines, each with a prefix."""

    def __init__(self, out_fd: int, default: int) -> None:
        self.out_fd = out_fd
        self.default = default
        self.partial = b""
        self.fatal = False  # after "Fatal Python error" the crash dump follows: all of it at 2

    def lines(self, data: bytes, final: bool = False) -> bytes:
        *lines, self.partial = (self.partial + data).split(b"\n")
        if final and self.partial:
            lines.append(self.partial)
            self.partial = b""
        out = []
        for line in lines:
            if _PREFIXED_B.match(line):
                out.append(line)
                continue
            if line.startswith(b"Fatal Python error"):
                self.fatal = True
            prio = CRIT if self.fatal else native_priority(line, self.default)
            out.append(b"<%d>%s" % (prio, line))
        return b"".join(x + b"\n" for x in out)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def _relay_main(pipes: dict[int, _Relay]) -> None:
    """The relay process: read each pipe to its end, write its lines prefixed to its output."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)  # robotd's shutdown writes its last lines after these
    sel = selectors.DefaultSelector()
    for fd in pipes:
        sel.register(fd, selectors.EVENT_READ)
    while sel.get_map():
        for key, _ in sel.select():
            relay = pipes[int(key.fd)]
            data = os.read(int(key.fd), 65536)
            _write_all(relay.out_fd, relay.lines(data, final=not data))
            if not data:
                sel.unregister(key.fd)


def _close_fds_except(keep: set[int]) -> None:
    lo = 3
    for fd in sorted(k for k in keep if k >= 3):
        os.closerange(lo, fd)
        lo = fd + 1
    os.closerange(lo, os.sysconf("SC_OPEN_MAX"))


def _start_relay(fds: dict[int, int]) -> None:
    """Point each of ``fds`` (fd -> default priority) at a pipe that a forked relay process reads
    and writes, prefixed, to what the fd was."""
    sys.stdout.flush()
    sys.stderr.flush()
    pipes = {fd: os.pipe() for fd in fds}
    pid = os.fork()
    if pid == 0:  # the relay: its fds 1 and 2 are still the journal
        code = 0
        try:
            for _, w in pipes.values():
                os.close(w)
            _close_fds_except({0, 1, 2, *(r for r, _ in pipes.values())})
            _relay_main({r: _Relay(fd, fds[fd]) for fd, (r, _) in pipes.items()})
        except BaseException:  # nothing to report to: the journal is what failed
            code = 1
        finally:
            os._exit(code)
    for fd, (r, w) in pipes.items():
        os.close(r)
        os.dup2(w, fd)
        os.close(w)


# ----------------------------------------------------------------------------------------------


def install() -> bool:
    """When stderr is the journal: prefixes on every line robotd's process writes (see the module
    docstring). Returns whether it did; once per process."""
    global _installed
    if _installed or not connected(2):
        return _installed
    fds = {2: STDERR_DEFAULT}
    if connected(1):
        fds[1] = STDOUT_DEFAULT
    _start_relay(fds)
    sys.stderr = PriorityStream(sys.stderr, STDERR_DEFAULT)
    atexit.register(sys.stderr.close)  # a last line without its newline still goes out, prefixed
    if 1 in fds:
        sys.stdout = PriorityStream(sys.stdout, STDOUT_DEFAULT)
        atexit.register(sys.stdout.close)
    _hook(ERR, WARNING)
    _installed = True
    return True


def _hook(error: int, warning: int) -> None:
    excepthook, thread_hook, unraisable = sys.excepthook, threading.excepthook, sys.unraisablehook
    showwarning = warnings.showwarning

    def on_exception(*args: Any) -> None:
        with priority(error):
            excepthook(*args)

    def on_thread_exception(args: Any) -> None:
        with priority(error):
            thread_hook(args)

    def on_unraisable(args: Any) -> None:
        with priority(warning):
            unraisable(args)

    def on_warning(*args: Any, **kwargs: Any) -> None:
        with priority(warning):
            showwarning(*args, **kwargs)

    sys.excepthook = on_exception
    threading.excepthook = on_thread_exception
    sys.unraisablehook = on_unraisable
    warnings.showwarning = on_warning
