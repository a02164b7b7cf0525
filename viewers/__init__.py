"""Viewers of the store: Rerun recordings of episodes and runs, reports and plots, comparisons, the OTLP export, and
stored text made safe to show (``safe_text``).

Rerun's own log (its Rust logger: a file it cannot write, a viewer it cannot reach) is off unless ``RUST_LOG`` says
otherwise. It writes to the process's stderr directly, past every Python-side safeguard, with colour escape sequences
even on a pipe or in a log file, and repeats what codearcade says itself in one line (the file that cannot be written,
the viewer that cannot be reached). Rerun reads ``RUST_LOG`` once, as its bindings load: so it is set here, before any
viewer imports ``rerun`` (only viewers do)."""

import os

os.environ.setdefault("RUST_LOG", "re_=off,rerun=off")  # Rerun's crates (re_sdk, re_grpc_client, ...); others as set
