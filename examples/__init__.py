"""The policy scaffolds of the three games (see README.md); loaded as policy files, never imported."""
