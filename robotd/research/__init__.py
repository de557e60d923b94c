"""Research code, apart from the daemon: the thesis's simulation experiments, landmark-world and
synthetic stereo simulators, trajectory evaluation (ATE/RPE/drift/NEES, TUM and KITTI files), the
batch least-squares bound, and dataset loaders that are not replay drivers (MRCLAM).

The daemon never imports this package (tests/test_layering.py enforces it); ``robotd replay``,
``robotd eval``, ``robotd experiments``, the benchmarks and the tests do.
"""
