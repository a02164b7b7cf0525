"""codearcade test suite."""
