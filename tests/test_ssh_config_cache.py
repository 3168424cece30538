"""The ssh config parsed once per process while it stays the same file (link/ssh.py's
load_ssh_config; a fleet push connects to every robot through it): a cached parse
answers exactly what a fresh one would, or is not used."""

from __future__ import annotations

import os
import time
from pathlib import Path

from fetchsync.link.ssh import load_ssh_config, resolve_host


def write(path: Path, port: int) -> None:
    path.write_text(f"Host r1\n    HostName 127.0.0.1\n    Port {port}\n")


def test_a_settled_config_is_parsed_once_and_a_rewrite_is_seen(tmp_path):
    cfg = tmp_path / "config"
    write(cfg, 2201)
    time.sleep(2.1)  # its stamps settle (a write after the read would move its ctime)
    first = load_ssh_config(cfg)
    assert load_ssh_config(cfg) is first
    assert resolve_host("r1", config=first).port == 2201
    # the same size, another port; its mtime put back as it was: the ctime moved
    st = cfg.stat()
    write(cfg, 2202)
    os.utime(cfg, ns=(st.st_atime_ns, st.st_mtime_ns))
    again = load_ssh_config(cfg)
    assert again is not first
    assert resolve_host("r1", config=again).port == 2202
    # replaced by another file under the same name
    other = tmp_path / "other"
    write(other, 2203)
    os.replace(other, cfg)
    assert resolve_host("r1", config=load_ssh_config(cfg)).port == 2203


def test_a_config_just_written_is_not_kept(tmp_path):
    cfg = tmp_path / "config"
    write(cfg, 2201)
    first = load_ssh_config(cfg)
    assert load_ssh_config(cfg) is not first  # written < 2 s ago: parsed each time
