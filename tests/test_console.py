"""Robot-controlled names are printed with their control characters escaped (issue 22 item 14)."""

from __future__ import annotations

import os

from helpers import fetchsync, local_env

from fetchsync.console import printable

EVIL = "evil\x1b]52;c;SGVsbG8=\x07\x1b[2J\u202e.txt"


def test_printable_escapes_controls_bidi_and_undecodable_bytes():
    assert printable(EVIL) == "evil\\x1b]52;c;SGVsbG8=\\x07\\x1b[2J\\u202e.txt"
    assert printable("line\nnext\r\x9b") == "line\\x0anext\\x0d\\x9b"
    assert printable(os.fsdecode(b"caf\xe9")) == "caf\\xe9"
    assert printable("plain/ünïcode name.cpp") == "plain/ünïcode name.cpp"


def test_names_from_the_robot_reach_the_terminal_escaped(tmp_path):
    env = local_env(
        tmp_path,
        FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "robot"),
        FETCHSYNC_REMOTE_WORKSPACE="~/ws",
    )
    fetchsync("push", env=env)
    robot = tmp_path / "robot/ws/src/my_pkg"
    (robot / EVIL).write_text("from the robot\n")
    (tmp_path / "ws/src/my_pkg" / ("local-" + EVIL)).write_text("laptop\n")
    (robot / ("local-" + EVIL)).write_text("the robot's own\n")  # a conflict on push
    outputs = [
        fetchsync("pull", "--dry-run", env=env, check=False),
        fetchsync("push", env=env, check=False),
    ]
    for proc in outputs:
        text = proc.stdout + proc.stderr
        assert b"\x1b" not in text and b"\x07" not in text and "\u202e".encode() not in text, text
    pulled = outputs[0].stdout.decode() + outputs[0].stderr.decode()
    assert printable(EVIL) in pulled
    pushed = outputs[1].stdout.decode() + outputs[1].stderr.decode()
    assert "conflict" in pushed and printable("local-" + EVIL) in pushed, pushed
