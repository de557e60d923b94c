"""Property tests with hypothesis over the parsers of hostile input (bounded in time: CI runs them)."""
