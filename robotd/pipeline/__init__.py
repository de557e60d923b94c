"""The pipeline layer (docs/architecture.md "Module map"): ``Pipeline.step`` (step.py), its stages
(stages/), relocalisation after a map load (relocalise.py), the motion across a gap no odometry
covers (stall.py), the vehicle's odometry gated and integrated (odometry.py) and one frame into
SLAM (feed.py), which the daemon and ``robotd replay`` share. Its configuration is robotd.config.
The core only; no I/O.
"""
