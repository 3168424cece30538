from fetchsync.trace import mark

mark("main: the interpreter is up")
from fetchsync.cli import main  # noqa: E402  (after the mark: its imports are measured)

main()
