from fetchsync.cli import main

main()
