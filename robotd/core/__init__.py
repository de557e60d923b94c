"""The core layer's own modules (docs/architecture.md "Module map"): the messages, errors and
algorithm names, geometry, the stereo camera model, the checks of saved state, the stage clock,
the numba decorator and the outlier stage. The core's two larger parts sit beside this package,
robotd.frontend and robotd.slam. Numeric libraries only; nothing here does I/O.
"""
