"""The daemon's state under the state directory (robotd.formats.persist): the reset counter file and the
map file, which is an input too (resumed before the first step) and then saved like any output."""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass

from robotd.config import Config
from robotd.formats.autopilot import ResetCounterPolicy
from robotd.formats.persist import CounterFile, default_state_dir
from robotd.outputs import enter_output
from robotd.outputs.mapfile import MapFileOutput
from robotd.pipeline.step import Pipeline
from robotd.slam.estimator import Persistent

logger = logging.getLogger("robotd.daemon")


@dataclass(frozen=True, slots=True)
class State:
    counter_file: CounterFile
    maps: MapFileOutput | None  # None: the filter cannot be saved or resumed
    resumed: bool  # the pipeline holds the saved map (a discontinuity for the autopilot)
    # the counter starts one above the last run's: the first pose is a new segment already
    new_segment: bool = False


def open_state(cfg: Config, stack: contextlib.ExitStack, pipeline: Pipeline, policy: ResetCounterPolicy) -> State:
    """The reset counter (``policy`` continues from the last run's) and the map file, resumed into
    ``pipeline`` when ``persistence.resume`` says so."""
    # the autopilot's view of robotd's pose stream: a new run is a new segment (its counter
    # differs from the last one the previous run sent)
    counter_file = CounterFile(default_state_dir(cfg.persistence.state_dir))
    last = counter_file.load()
    if last is not None:
        policy.counter = (last + 1) & 0xFF
        logger.info("reset_counter starts at %d (the last run sent %d)", policy.counter, last)
    counter_file.save(policy.counter)
    # the map file is an input too: resume before the first step, then save like any output
    if not isinstance(pipeline.estimator, Persistent):
        logger.warning("map file: none (the %r filter cannot be saved or resumed)", pipeline.estimator.name)
        return State(counter_file, None, False, last is not None)
    maps = enter_output(stack, MapFileOutput(cfg.persistence, cfg.robot.id))
    resumed = cfg.persistence.resume and maps.resume(pipeline)
    return State(counter_file, maps, bool(resumed), last is not None)
