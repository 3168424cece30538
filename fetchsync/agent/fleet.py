"""One watcher, several robots: ``fetchsync watch --robot a,b`` (or ``@group``).

The laptop's tree is watched once (one inotify scan, one coalescer) and each batch
is handed to every robot's :class:`~fetchsync.agent.service.Agent`, which holds its
own connection, last-synced state, control socket and reconnect loop. So a robot
that is offline keeps its changes and catches up by itself once it is back, while
the others go on receiving saves; ``fetchsync status --robot NAME`` and ``flush
--robot NAME`` talk to one robot's agent exactly as for a single watch.

The fleet has a control socket of its own, keyed by the local workspace: it answers
``status`` with the robots and their sockets, so ``fetchsync status`` and ``flush``
without ``--robot`` find every robot of the watch running on this workspace.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from fetchsync.agent.control import ControlServer, runtime_paths
from fetchsync.agent.service import Agent, take_lock
from fetchsync.errors import UsageError

STOP_JOIN = 3.0  # seconds to wait for each robot's agent to wind down (its own joins take 2)


def fleet_paths(src: str | os.PathLike[str]) -> tuple[Path, Path]:
    """The lock file and the control socket of the fleet watch of the local ``src``."""
    return runtime_paths("fleet", b"fleet\0" + os.fsencode(os.path.realpath(src)))


class FleetWatch:
    """Watches ``src`` once and feeds each batch to every robot's agent (``own_watcher=False``)."""

    def __init__(
        self,
        agents: Sequence[Agent],
        *,
        src: str,
        rules: Any,
        say: Callable[[str], None],
        quiet: float | None = None,
        cap: float | None = None,
    ) -> None:
        if not agents:
            raise UsageError("a fleet watch needs at least one robot")
        self.agents = list(agents)
        self.src = src
        self.rules = rules
        self.say = say
        self.quiet = quiet
        self.cap = cap
        self.stop_event = threading.Event()
        self._lock_fd = -1
        self.socket_path: Path | None = None

    # ------------------------------------------------------------------ lifecycle
    def acquire(self) -> None:
        """Take the fleet's lock for ``src`` and each robot's agent lock, or none of them."""
        lock, sock = fleet_paths(self.src)
        fd = take_lock(
            lock,
            lambda owner: UsageError(
                f"a fleet watch of {self.src} is already running ({owner})",
                hint="stop it first, or use fetchsync status / flush",
            ),
        )
        taken: list[Agent] = []
        try:
            for agent in self.agents:
                agent.acquire()
                taken.append(agent)
        except BaseException:
            for agent in taken:
                agent.release()
            os.close(fd)
            raise
        self._lock_fd = fd
        self.socket_path = sock

    def release(self) -> None:
        for agent in self.agents:
            agent.release()
        if self._lock_fd >= 0:
            os.close(self._lock_fd)
            self._lock_fd = -1

    def run(self) -> None:
        """Watch and feed every robot until :meth:`stop`; returns within a few seconds of it."""
        assert self.socket_path is not None, "acquire() first"
        server = _FleetServer(self.socket_path, self)
        server.start()
        runners = [
            threading.Thread(
                target=agent.run, name=f"fetchsync-robot-{agent.target.robot}", daemon=True
            )
            for agent in self.agents
        ]
        for thread in runners:
            thread.start()
        watcher = threading.Thread(target=self._watch, name="fetchsync-watch", daemon=True)
        watcher.start()
        try:
            while not self.stop_event.wait(0.2):
                pass
        finally:
            for agent in self.agents:
                agent.stop()
            for thread in runners:
                thread.join(STOP_JOIN)
            watcher.join(0.5)
            server.stop()

    def stop(self) -> None:
        self.stop_event.set()

    def status(self) -> dict[str, Any]:
        """The robots of this watch and where each one's agent answers."""
        return {
            "pid": os.getpid(),
            "workspace": self.src,
            "robots": [
                {"robot": agent.target.robot, "socket": str(agent.socket_path)}
                for agent in self.agents
            ],
        }

    # ------------------------------------------------------------------ the one watcher
    def _watch(self) -> None:
        from fetchsync.agent.watcher import batches

        kwargs: dict[str, Any] = {}
        if self.quiet is not None:
            kwargs["quiet"] = self.quiet
        if self.cap is not None:
            kwargs["cap"] = self.cap
        try:
            for batch in batches(self.src, rules=self.rules, stop_event=self.stop_event, **kwargs):
                for agent in self.agents:
                    # each agent merges the batch into its own pending work: one that is
                    # offline keeps it until it is back, and holds no one else up
                    if batch.rescan:
                        agent.request(full=True)
                    else:
                        agent.request(paths=set(batch.paths), dirs=set(batch.dirs))
        except Exception as exc:  # no robot can be kept up to date without the watcher
            self.say(f"error: watcher failed: {exc}")
            self.stop()


class _FleetServer(ControlServer):
    """The fleet's socket: ``status`` lists the robots and their agents' sockets (which
    answer ``status``, ``flush`` and ``push`` themselves)."""

    def handle(self, req: dict[str, Any]) -> dict[str, Any]:
        if req.get("cmd") == "status":
            return {"ok": True, "fleet": self.agent.status()}
        raise ValueError(f"unknown command {req.get('cmd')!r} (ask a robot's agent)")
