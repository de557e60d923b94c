"""The daemon's outputs, built from the config (docs/architecture.md, "Adding an output").

Each output is one module here with a class derived from :class:`robotd.outputs.base.Output` and
a factory ``make(ctx) -> Output | None`` that reads its own config section and returns None when
it is off. :data:`FACTORIES` lists them in the order they are opened (and closed in reverse) and
called. A new output is one module plus one line here plus its config section; the daemon calls
it through :class:`robotd.outputs.runner.OutputRunner`, under the one error policy every output has.

The map file is not in the list: it is also an input (``persistence.resume`` restores the
pipeline from it before the first step), so the daemon opens it itself and puts it first.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any

from drivers import AutopilotLink
from robotd.config import Config
from robotd.core.stereo import RectifiedStereo
from robotd.outputs.base import Output, StepReport, pose_quality
from robotd.outputs.runner import OutputRunner, enter_output


@dataclass(frozen=True, slots=True)
class OutputContext:
    """What the factories may build an output from."""

    cfg: Config
    rig: RectifiedStereo
    autopilot: AutopilotLink | None = None  # the pose sink of the vehicle (or of a separate MAVLink link)
    record_path: str | None = None  # robotd record OUT.mcap
    session_meta: dict[str, Any] = field(default_factory=dict)  # facts about the run for recordings
    raw_calibration: Any = None  # the camera's own calibration dump (OAK EEPROM), for recordings
    record_buffer_mb: float | None = None  # images that may wait for the recorder's writer (None: its default)


def _recorder(ctx: OutputContext) -> Output | None:
    if not ctx.record_path:
        return None
    from robotd.outputs.recorder import RecorderOutput

    if ctx.record_buffer_mb is None:
        return RecorderOutput(ctx.record_path, ctx.rig, ctx.session_meta, ctx.raw_calibration)
    return RecorderOutput(ctx.record_path, ctx.rig, ctx.session_meta, ctx.raw_calibration, ctx.record_buffer_mb)


def _zenoh(ctx: OutputContext) -> Output | None:
    if not ctx.cfg.zenoh.enabled:
        return None
    from robotd.outputs.zenoh import ZenohOutput

    return ZenohOutput(ctx.cfg.zenoh, ctx.cfg.robot.id)


def _liveview(ctx: OutputContext) -> Output | None:
    if not ctx.cfg.liveview.enabled:
        return None
    from robotd.outputs.liveview import LiveViewOutput

    return LiveViewOutput(ctx.cfg.liveview, ctx.rig, ctx.cfg.robot.id, ctx.raw_calibration)


def _autopilot(ctx: OutputContext) -> Output | None:
    if ctx.autopilot is None:
        return None
    from robotd.outputs.autopilot_link import AutopilotOutput

    return AutopilotOutput(ctx.autopilot)


# (name, factory), in the order outputs are opened and called. The network session first: when
# it cannot open (a second robotd holding the port), the start fails before a file is created.
FACTORIES: tuple[tuple[str, Callable[[OutputContext], Output | None]], ...] = (
    ("zenoh", _zenoh),  # [zenoh] enabled
    ("liveview", _liveview),  # [liveview] enabled: the Foxglove app, live (a port, like zenoh: before any file)
    ("recorder", _recorder),  # robotd record OUT.mcap
    ("autopilot", _autopilot),  # [mavlink] enabled, or a vehicle link with an autopilot role
)


def build_outputs(ctx: OutputContext, stack: ExitStack) -> list[Output]:
    """Open every output the config asks for; each is closed when ``stack`` unwinds (a failing
    close is logged and the others still close: robotd.outputs.runner.enter_output)."""
    outputs: list[Output] = []
    for _, make in FACTORIES:
        out = make(ctx)
        if out is not None:
            outputs.append(enter_output(stack, out))
    return outputs


__all__ = [
    "FACTORIES",
    "Output",
    "OutputContext",
    "OutputRunner",
    "StepReport",
    "build_outputs",
    "enter_output",
    "pose_quality",
]
