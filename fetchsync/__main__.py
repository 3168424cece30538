"""``python -m fetchsync`` and the ``fetchsync`` console command.

A plain ``push`` is first offered to a warm resident (:func:`fetchsync.agent.quick.fast_main`)
without importing click or the engine; everything else, and a push no resident
makes, goes to the CLI (:mod:`fetchsync.cli`).
"""

from fetchsync.trace import mark


def main() -> None:
    mark("main: the interpreter is up")
    import sys

    from fetchsync.agent.quick import fast_main

    code = fast_main(sys.argv[1:])
    if code is not None:
        _exit(code)
    from fetchsync.cli import main as cli_main

    cli_main()


def _exit(code: int) -> None:
    """As the CLI ends (fetchsync.cli._exit): output flushed, no interpreter teardown."""
    import os
    import sys

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            code = code or 1
    mark("exit: output flushed")
    os._exit(code)


if __name__ == "__main__":
    main()
