"""Property tests (hypothesis) of the parsers and loaders; tests/fuzz/ mirrors no source directory."""
