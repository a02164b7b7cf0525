"""The DuckDB event store: schema and migrations, per-use attachments, batched writers, slice readers.

The store is codearcade's public API: everything a run does lands here, and the optimizer and viewers read
only from here. See docs/schema.md for the tables.
"""

from store.locate import DEFAULT_STORE, StoreLocation, locate_store

__all__ = ["Store", "StoreError", "StoreLocation", "DEFAULT_STORE", "default_store_path", "locate_store"]

_FROM_DB = ("Store", "StoreError", "default_store_path")


def __getattr__(name: str):
    """``Store``, ``StoreError`` and ``default_store_path``, taken from ``store.db`` when first asked for: importing
    the package or a module of it that needs no database (``store.scores``, as ``codearcade --help`` does) does not
    import DuckDB, pyarrow and numpy (~0.15 s)."""
    if name in _FROM_DB:
        from store import db

        return getattr(db, name)
    raise AttributeError(f"module 'store' has no attribute {name!r}")
