"""The DuckDB event store: schema and migrations, per-use attachments, batched writers, slice readers.

The store is codearcade's public API: everything a run does lands here, and the optimizer and viewers read
only from here. See docs/schema.md for the tables.
"""

from store.db import Store, StoreError, default_store_path
from store.locate import DEFAULT_STORE, StoreLocation, locate_store

__all__ = ["Store", "StoreError", "StoreLocation", "DEFAULT_STORE", "default_store_path", "locate_store"]
