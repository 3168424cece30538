"""The sync engine, laptop side: push and pull over one connection.

``engine`` (``Syncer`` and the per-push ``Round``), ``plan`` (the pure
``reconcile``), ``state`` (what was last synced, in SQLite).
"""
