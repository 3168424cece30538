"""Click commands for the verbs beyond push and pull, one module each, loaded lazily.

Each module exports ``command`` (a ``click.Command``); ``fetchsync.cli``
lists the finished ones in ``LAZY_COMMANDS`` and imports a module only when
its verb is used, so start-up stays fast.
"""
