"""Where a push's bytes go: payload bytes per message kind, both directions.

Runs ``fetchsync push`` in this process against the built-in ``local`` robot
(no SSH: the figures are fetchsync's own frames, without SSH's framing and
handshake, which the bench's countproxy adds) and tallies every frame by the
request it belongs to: out = the request frames, in = their answers; ``hello``
is the handshake (and the endpoint's archive when the robot had to be sent
it). Bytes are deterministic, so this needs no quiet machine.

    python3 bench/acct.py [--files 300 --size-mb 5] [--history N]
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fetchsync.link import connection as conn_mod  # noqa: E402
from fetchsync.protocol import wire  # noqa: E402

OUT: collections.Counter[str] = collections.Counter()
IN: collections.Counter[str] = collections.Counter()
FRAMES: collections.Counter[str] = collections.Counter()
SOURCES: collections.Counter[str] = collections.Counter()  # ops by source, raw blob bytes
_ops: dict[int, str] = {}


def _install() -> None:
    enc, enc_parts, read = wire.encode_frame, wire.encode_frame_parts, wire.Reader.read_frame
    opened = conn_mod.Connection._open.__func__  # type: ignore[attr-defined]

    def encode_frame(frame, **kw):  # type: ignore[no-untyped-def]
        data = enc(frame, **kw)
        op = str(frame.header.get("op", "?"))
        _ops[frame.req_id] = op
        OUT[op] += len(data)
        FRAMES[op + ">"] += 1
        return data

    def encode_frame_parts(frame, parts, **kw):  # type: ignore[no-untyped-def]
        data = enc_parts(frame, parts, **kw)
        op = str(frame.header.get("op", "?"))
        _ops[frame.req_id] = op
        OUT[op + " head"] += len(data[0])
        for o in frame.header.get("ops", ()):
            kind = "z" if o.get("z") else "raw"
            SOURCES[f"{o.get('src', o.get('k'))}/{kind}"] += 1
            SOURCES[f"{o.get('src', o.get('k'))}/{kind} bytes"] += (o.get("bl") or [0, 0])[1]
        OUT[op + " blob"] += sum(len(p) for p in data[1:])
        FRAMES[op + ">"] += 1
        return data

    def read_frame(self):  # type: ignore[no-untyped-def]
        before = self.bytes_in - len(self._buf)
        frame = read(self)
        if frame is not None:
            after = self.bytes_in - len(self._buf)
            op = _ops.get(frame.req_id, "?")
            if frame.type == wire.T_PROGRESS:
                op = "progress"
            IN[op] += after - before
            FRAMES["<" + op] += 1
        return frame

    def _open(cls, transport, python, meanwhile, *rest):  # type: ignore[no-untyped-def]
        c = opened(cls, transport, python, meanwhile, *rest)
        OUT["hello"] += c.bytes_out
        IN["hello"] += c.reader.bytes_in - len(c.reader._buf)
        return c

    wire.encode_frame = encode_frame  # type: ignore[assignment]
    wire.encode_frame_parts = encode_frame_parts  # type: ignore[assignment]
    wire.Reader.read_frame = read_frame  # type: ignore[method-assign]
    conn_mod.Connection._open = classmethod(_open)  # type: ignore[assignment]


def push(label: str, rows: list[tuple[str, dict[str, int], dict[str, int]]]) -> None:
    from fetchsync.cli import cli

    OUT.clear()
    IN.clear()
    FRAMES.clear()
    SOURCES.clear()
    with contextlib.redirect_stdout(io.StringIO()):
        try:
            cli.main(["push", "--json"], standalone_mode=False)
        except SystemExit:
            pass
    rows.append((label, dict(OUT), dict(IN)))
    if os.environ.get("ACCT_SOURCES"):
        print(label, dict(SOURCES), file=sys.stderr)


def show(rows: list[tuple[str, dict[str, int], dict[str, int]]]) -> None:
    for label, out, inn in rows:
        print(
            f"{label:28s} out {sum(out.values()):9d}  in {sum(inn.values()):7d}  "
            + "  ".join(f"{k}>{v}" for k, v in sorted(out.items()))
            + "  |  "
            + "  ".join(f"<{k} {v}" for k, v in sorted(inn.items()))
        )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--files", type=int, default=300)
    ap.add_argument("--size-mb", type=float, default=5)
    ap.add_argument("--history", type=int, default=0, help="rclcpp commits to replay")
    ap.add_argument("--switches", type=int, default=0, help="release switches after them")
    ap.add_argument("--bundle", default="/work/shared/data/rclcpp.bundle")
    ap.add_argument("--json")
    args = ap.parse_args()
    _install()
    tmp = Path(tempfile.mkdtemp(prefix="acct-"))
    os.environ.update(
        FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp / "robot-home"),
        XDG_STATE_HOME=str(tmp / "state"),
        XDG_CACHE_HOME=str(tmp / "cache"),
        XDG_RUNTIME_DIR=str(tmp / "run"),
        FETCHSYNC_ROBOT="local",
        FETCHSYNC_WORKSPACE=str(tmp / "ws"),
        FETCHSYNC_REMOTE_WORKSPACE="~/robot_ws",
    )
    (tmp / "run").mkdir(mode=0o700)
    rows: list[tuple[str, dict[str, int], dict[str, int]]] = []
    try:
        if args.history:
            src = tmp / "ws" / "src"
            src.mkdir(parents=True)
            git = ["git", "--git-dir", str(tmp / "git"), "--work-tree", str(src / "rclcpp")]
            subprocess.run(
                ["git", "clone", "-q", "--bare", args.bundle, str(tmp / "git")], check=True
            )
            (src / "rclcpp").mkdir()
            revs = subprocess.run(
                git + ["rev-list", "--first-parent", f"-{args.history + 1}", "HEAD"],
                check=True,
                capture_output=True,
                text=True,
            ).stdout.split()[::-1]
            subprocess.run(git + ["checkout", "-q", "-f", revs[0]], check=True)
            push("initial rclcpp", rows)
            push("no-op", rows)
            for rev in revs[1:]:
                subprocess.run(git + ["checkout", "-q", "-f", rev], check=True)
                push("commit " + rev[:7], rows)
            if args.switches:
                from history import RELEASE, switch_plan

                log = subprocess.run(
                    git + ["log", "--first-parent", "--format=%H %s", "HEAD"],
                    check=True,
                    capture_output=True,
                    text=True,
                ).stdout
                releases = []
                for line in log.splitlines():
                    sha, _, subject = line.partition(" ")
                    m = RELEASE.match(subject.strip())
                    if m:
                        releases.append(((int(m[1]), int(m[2]), int(m[3])), sha))
                for version, sha in switch_plan(releases, args.switches):
                    subprocess.run(git + ["checkout", "-q", "-f", sha], check=True)
                    push("switch " + version, rows)
        else:
            import workspace
            from run import Edits

            ws = workspace.generate(tmp / "ws", files=args.files, size_mb=args.size_mb)
            edits = Edits(ws)
            push("initial", rows)
            push("no-op", rows)
            edits.one_edit(1)
            push("one-edit", rows)
            edits.insert_top(1)
            push("insert 2 MiB", rows)
            edits.rename(1)
            push("rename", rows)
        states = list((tmp / "state").rglob("*.sqlite*"))
        print(
            "laptop state: %d bytes; this process's CPU: %.2f s"
            % (sum(f.stat().st_size for f in states), time.process_time())
        )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    show(rows)
    if args.history:
        switches = [r for r in rows if r[0].startswith("switch")]
        if switches:
            tot = sum(sum(o.values()) + sum(i.values()) for _, o, i in switches)
            print(f"switches: {len(switches)}, both ways in all {tot}")
        commits = [r for r in rows if r[0].startswith("commit")]
        tot = sum(sum(o.values()) + sum(i.values()) for _, o, i in commits)
        print(f"commits: {len(commits)}, both ways in all {tot}")
        agg: collections.Counter[str] = collections.Counter()
        for _, o, i in commits:
            agg.update({k + ">": v for k, v in o.items()})
            agg.update({"<" + k: v for k, v in i.items()})
        print("  ".join(f"{k} {v}" for k, v in sorted(agg.items())))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
