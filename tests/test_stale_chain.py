"""A round's batches sent behind one refused as stale are refused too.

The laptop pipelines a round's batches as generations gen, gen+1, ...; a robot
another writer moved k generations on refuses batches 0..k-1 and, without the
endpoint's check, applied batch k and later (an upload's last pieces without its
first: a hash failure; writes of a plan made against a tree that is gone). The
endpoint refuses them until the client lists or opens again, as it always does
before it plans anew. Checked against the real endpoint (the ``local`` robot),
the other writer on a second connection.
"""

from __future__ import annotations

from pathlib import Path

from fetchsync.link import client as C
from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.protocol import messages as M
from fetchsync.protocol.ignore import build_rules


def _mkdir(name: str) -> list[M.Op]:
    return [M.Op(M.MKDIR, name, expect=M.ABSENT, mode=0o755)]


def test_batches_behind_a_stale_one_are_refused_until_the_client_lists(tmp_path: Path) -> None:
    home = tmp_path / "robot-home"
    ours = Connection.open(LocalTransport(home))
    theirs = Connection.open(LocalTransport(home))
    try:
        mine, other = C.Endpoint(ours), C.Endpoint(theirs)
        opened = mine.open("~/ws", rules=build_rules())
        epoch, gen = opened.epoch, opened.gen
        other.open("~/ws", rules=build_rules())
        for k, name in enumerate(("w1", "w2")):  # another laptop's push: two batches
            applied = other.send_sync(_mkdir(name), policy="preserve", epoch=epoch, gen=gen + k)
            assert not applied.wait().stale
        # our round, planned at ``gen``: three batches pipelined as the batcher chains them
        chain = [
            mine.send_sync(_mkdir(f"b{k}"), policy="preserve", epoch=epoch, gen=gen + k)
            for k in range(3)
        ]
        assert [p.wait().stale for p in chain] == [True, True, True]
        src = home / "ws" / "src"
        assert sorted(p.name for p in src.iterdir()) == ["w1", "w2"]
        listing = mine.listing()  # the client starts again from what the robot holds
        again = mine.send_sync(_mkdir("b2"), policy="preserve", epoch=epoch, gen=listing.gen)
        assert not again.wait().stale and (src / "b2").is_dir()
    finally:
        ours.close()
        theirs.close()
