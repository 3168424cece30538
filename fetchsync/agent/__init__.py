"""The long-running local agent: watcher, coalescer, sync loop, control socket."""
