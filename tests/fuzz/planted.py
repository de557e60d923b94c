"""A fuzz target with planted faults, for tests/fuzz/test_fuzz_bench.py: ``python -m
tests.fuzz.planted ARGS`` runs bench/fuzz.py's main with it added as ``faulty``, in a process of
its own (the bench forks its workers; a fork of the test process would inherit its threads)."""

from __future__ import annotations

import importlib.util
import os
import random
import signal
import sys
import time

import numpy as np

from tests.fuzz.targets import TARGETS, Case
from tests.support.paths import REPO


class Faulty:
    """A target with planted faults: byte 0-9 an exception, 10 the worker killed by a signal,
    11-13 a hang, 14 100 MB allocated; everything else clean."""

    name = "faulty"

    def setup(self) -> None:
        pass

    def generate(self, rng: random.Random) -> Case:
        return Case(bytes([rng.randrange(100)]))

    def check(self, case: Case) -> str:
        b = case.data[0]
        if b < 10:
            raise KeyError(f"planted {b}")
        if b == 10:
            os.kill(os.getpid(), signal.SIGKILL)  # as the OOM killer does
        if b in (11, 12, 13):
            time.sleep(30)
        if b == 14:  # returns normally, but having used 100 MB (a forged size believed)
            return "clean" if np.ones(12_500_000).sum() else "?"
        return "clean"


def main(argv: list[str]) -> int:
    spec = importlib.util.spec_from_file_location("bench_fuzz", REPO / "bench" / "fuzz.py")
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    sys.modules["bench_fuzz"] = bench  # its dataclasses look their module up there
    spec.loader.exec_module(bench)
    TARGETS["faulty"] = Faulty
    return int(bench.main(argv))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
