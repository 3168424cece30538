#!/usr/bin/env python3
"""The sending thread's CPU per MiB of channel data, packets in runs or one by one.

    python3 bench/channelab.py [--mib 16] [--reps 8]

A real sshd on loopback (tests/sshd.py), one SSH connection; each repetition sends
``--mib`` MiB of random data to ``cat > /dev/null`` with channels.RUN = 8 (runs) and
RUN = 1 (a packet at a time, as before runs), interleaved, and reports the sending
thread's CPU (time.thread_time: its own, however loaded the machine is) and the socket
writes made (channels.Packetizer.write_all calls). Issue 27, fleet track: a fleet push's
sender threads (one per robot) spent ~55 us per 32 KiB packet, mostly Python.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
for _p in (str(REPO), str(REPO / "tests")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from sshd import make_ssh_home, running_sshd  # noqa: E402

from fetchsync.link import channels  # noqa: E402
from fetchsync.link.ssh import SSHTransport  # noqa: E402


def one(transport: SSHTransport, data: bytes, run: int) -> tuple[float, int]:
    """(sender CPU seconds, socket writes) for ``data`` sent with runs of ``run``."""
    channels.RUN = run
    pk = transport._transport.packetizer
    writes = [0]
    real = pk.write_all

    def counted(out: object) -> None:
        writes[0] += 1
        real(out)

    pk.write_all = counted
    chan = transport.exec("cat > /dev/null")
    t0 = time.thread_time()
    chan.send_all(memoryview(data))
    cpu = time.thread_time() - t0
    chan.shutdown_write()
    assert chan.exit_status(timeout=60) == 0
    chan.close()
    del pk.write_all
    return cpu, writes[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mib", type=int, default=16)
    ap.add_argument("--reps", type=int, default=8)
    args = ap.parse_args()
    data = os.urandom(args.mib * 2**20)
    with tempfile.TemporaryDirectory(prefix="channelab-") as tmp:
        with running_sshd(Path(tmp) / "sshd") as sshd:
            home = make_ssh_home(Path(tmp) / "home", sshd=sshd)
            os.environ["HOME"] = str(home.home)
            os.environ.pop("SSH_AUTH_SOCK", None)
            transport = SSHTransport.connect("robot", connect_timeout=10.0)
            try:
                got: dict[int, list[tuple[float, int]]] = {8: [], 1: []}
                one(transport, data, 8)  # warm up
                for rep in range(args.reps):
                    for run in (8, 1) if rep % 2 == 0 else (1, 8):
                        got[run].append(one(transport, data, run))
                    load = os.getloadavg()[0]
                    print(
                        f"rep {rep} load {load:4.1f}: runs {got[8][-1][0] * 1e3 / args.mib:6.2f}"
                        f" ms/MiB, one by one {got[1][-1][0] * 1e3 / args.mib:6.2f} ms/MiB",
                        flush=True,
                    )
            finally:
                transport.close()
    for run, rows in got.items():
        cpu = [c * 1e3 / args.mib for c, _ in rows]
        packets = args.mib * 2**20 / (32 * 1024 - 64)
        print(
            f"RUN={run}: sender CPU median {statistics.median(cpu):.2f} ms/MiB "
            f"(min {min(cpu):.2f}, max {max(cpu):.2f}) = "
            f"{statistics.median(cpu) * args.mib * 1e3 / packets:.1f} us per 32 KiB packet; "
            f"socket writes {statistics.median(w for _, w in rows):.0f} for {args.mib} MiB"
        )


if __name__ == "__main__":
    main()
