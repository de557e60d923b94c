"""The stages of ``Pipeline.step`` (robotd/pipeline/step.py), one object per cohesive group, and the
state each keeps between frames.

A stage the step times is a method decorated with its name (:func:`robotd.core.timing.stage`) on an
object that holds the step's clock: the step calls it as a plain method, and its milliseconds
are ``StepResult.timings_ms[name]``. The objects, in data-flow order:

- ``measure.py``: :class:`~robotd.pipeline.stages.measure.Measure`, the front end's stages (detect, stereo,
  motion, identify, outliers) and select, which caps the filter's work and commits the frame's
  new landmarks;
- ``motion.py``: :class:`~robotd.pipeline.stages.motion.MotionModel`, the motion prior the images are
  checked against, the increment the filter predicts with (odometry, the images' motion or
  constant velocity) and the constant-velocity model;
- ``gap.py``: :class:`~robotd.pipeline.stages.gap.Gap`, a gap no odometry covers, and the stage that
  bridges it (robotd.pipeline.stall);
- ``relocalising.py``: :class:`~robotd.pipeline.stages.relocalising.Relocalising`, the frames after a map
  load, until the map is found (robotd.pipeline.relocalise);
- ``fuse.py``: :class:`~robotd.pipeline.stages.fuse.Fuse`, the filter's stages: predict, consistency, update;
- ``attitude.py``: :class:`~robotd.pipeline.stages.attitude.Attitude`, the vehicle's gravity into the
  filter and an attitude no rover can have reset to level;
- ``tracking.py``: what the step counts and whether it is tracking.

The pipeline builds them once, each with the objects it works on; none imports the pipeline.
"""
