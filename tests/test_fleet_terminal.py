"""At a terminal, a fleet's connections open side by side: only a question waits.

Against the real sshd, on a pseudo-terminal (a user at a terminal has one, the bench and
CI do not): a robot whose link stalls (it takes the connection and never says a word)
must not hold the others back."""

from __future__ import annotations

import os
import select
import socket
import threading

import pytest
from helpers import tree_of
from test_fleet import ROBOTS, _src, fleet_env  # noqa: F401

pytestmark = [pytest.mark.ssh, pytest.mark.slow]


def test_at_a_terminal_a_stalled_robot_does_not_hold_the_others_back(
    fleet_env,  # noqa: F811
    ssh_home,
    tmp_path,
):
    from terminal import Terminal

    src = _src(fleet_env)
    seen: dict[str, bool] = {}

    def all_pushed() -> bool:
        try:
            return all(tree_of(tmp_path / f"robot-{n}/src") == tree_of(src) for n in ROBOTS)
        except FileNotFoundError:  # a push's temporary, renamed while the tree was read
            return False

    def hold(listener: socket.socket) -> None:
        """Take the stalled robot's connection and say nothing: until the other robots
        are pushed (then let it go) or its client gives up on it."""
        conn, _ = listener.accept()
        with conn:
            while True:
                if all_pushed():
                    seen["others done while it stalled"] = True
                    return
                if select.select([conn], [], [], 0.05)[0] and not conn.recv(4096):
                    seen["its client gave up first"] = True
                    return

    with socket.socket() as stalled:
        stalled.bind(("127.0.0.1", 0))
        stalled.listen(8)
        holder = threading.Thread(target=hold, args=(stalled,), daemon=True)
        holder.start()
        config = ssh_home.config.read_text()
        block = config[config.index("Host fetch1") :].split("\nHost ", 1)[0]
        ssh_home.config.write_text(
            config
            + "\n"
            + block.replace("Host fetch1", "Host stalled", 1).replace(
                f"Port {ssh_home.sshd.port}", f"Port {stalled.getsockname()[1]}"
            )
            + "\n"
        )
        env = dict(fleet_env, PYTHONPATH=os.environ.get("PYTHONPATH", ""))
        # the stalled robot first: with the connections opened one at a time (as before),
        # the others waited behind its handshake until it timed out
        term = Terminal(["push", "--robot", "stalled,fetch1,fetch2,fetch3"], env, cols=200)
        try:
            status = term.wait(90)
        finally:
            term.close()
        holder.join(10)
    out = term.output.decode(errors="replace")
    assert seen == {"others done while it stalled": True}, (seen, out)
    assert status == 3, out  # the stalled robot failed, the others did not
    assert all_pushed(), out
