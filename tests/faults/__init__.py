"""Fault-injection suite: hostile code and replies, kills, and bad inputs at the edges (see docs/sandbox.md)."""
