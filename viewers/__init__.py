"""Viewers of the store: Rerun recordings of episodes and runs, reports and plots, comparisons, the OTLP export, and
stored text made safe to show (``safe_text``)."""
