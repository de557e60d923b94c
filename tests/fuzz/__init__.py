"""Property (fuzz) tests with hypothesis across the packages: bounded in time, run in CI."""
