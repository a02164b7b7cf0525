"""Viewers of the store: Rerun recordings of episodes and runs, reports and plots (being built)."""
