"""A malicious robot: the real endpoint, speaking the real wire protocol, that lies.

Run as ``python hostile_endpoint.py MODE CANARY`` in place of the loader (see
``test_hostile.py``): it serves a real store under the requested workspace,
but its listings and file contents are forged according to MODE, or it
breaks the framing itself. CANARY is a directory outside the workspace that a
correct client must never write into.
"""

from __future__ import annotations

import os
import struct
import sys
from typing import Any, Dict, List, Tuple

from fetchsync.protocol import hashing, wire
from fetchsync.protocol.server import Server

MODES = (
    "dotdot",
    "absolute",
    "nul",
    "slash",
    "empty_name",
    "symlink_escape",
    "wrong_content",
    "oversized_frame",
    "garbage_after_hello",
    "huge_header",
)


class HostileServer(Server):
    def __init__(self, mode: str, canary: str) -> None:
        out = os.fdopen(os.dup(1), "wb")
        os.dup2(2, 1)
        super().__init__(sys.stdin.buffer, out)
        self.mode = mode
        self.canary = canary
        self.payload = b"pwned by a hostile robot\n"

    def _hash(self, data: bytes) -> str:
        return hashing.digest(self.algorithm, data).hex()

    def _evil_entries(self) -> List[List[Any]]:
        h, n = self._hash(self.payload), len(self.payload)
        rel_canary = os.path.relpath(self.canary, self.store.root)  # "../canary"
        if self.mode == "dotdot":
            return [[rel_canary + "/evil.txt", "f", 0o644, n, h]]
        if self.mode == "absolute":
            return [[os.path.join(self.canary, "evil.txt"), "f", 0o644, n, h]]
        if self.mode == "nul":
            return [["my_pkg/evil\x00.txt", "f", 0o644, n, h]]
        if self.mode == "slash":
            return [["my_pkg//evil.txt", "f", 0o644, n, h], ["my_pkg/evil/", "f", 0o644, n, h]]
        if self.mode == "empty_name":
            return [["", "f", 0o644, n, h]]
        if self.mode == "symlink_escape":
            # a link out of the workspace, then files "inside" it
            return [
                ["escape", "l", 0, 0, self.canary],
                ["escape/evil.txt", "f", 0o644, n, h],
                ["escape/sub", "d", 0o755, 0, ""],
                ["escape/sub/evil.txt", "f", 0o644, n, h],
            ]
        if self.mode == "wrong_content":
            return [["my_pkg/lie.txt", "f", 0o644, n, self._hash(b"something else entirely\n")]]
        return []

    def do_list(self, h: Dict[str, Any], blob: bytes) -> Tuple[Dict[str, Any], bytes]:
        out, data = super().do_list(h, blob)
        out["full"] = True
        out["entries"] = list(out.get("entries", [])) + self._evil_entries()
        return out, data

    def do_read(self, h: Dict[str, Any], blob: bytes) -> Tuple[Dict[str, Any], bytes]:
        forged = {e[0]: e for e in self._evil_entries()}
        answers, parts, pos = [], [], 0
        items = h.get("items") or []
        real = [i for i in items if i.get("p") not in forged]
        real_out, real_blob = (
            super().do_read(dict(h, items=real), blob) if real else ({"items": []}, b"")
        )
        real_answers = iter(real_out["items"])
        for item in items:
            entry = forged.get(item.get("p"))
            if entry is None:
                ans = dict(next(real_answers))
                off, length = ans["bl"]
                data = real_blob[off : off + length]
            else:
                data = self.payload
                ans = {"c": "ok", "l": entry, "src": "data"}
            ans["bl"] = [pos, len(data)]
            answers.append(ans)
            parts.append(data)
            pos += len(data)
        return {"items": answers}, b"".join(parts)

    def _send(self, frame: wire.Frame) -> None:
        if self.mode == "oversized_frame" and frame.header.get("entries") is not None:
            # announce a frame far over the cap, then keep sending
            self.out.write(
                struct.pack(">IBBI", wire.MAX_FRAME + 1, wire.T_RESPONSE, 0, frame.req_id)
            )
            self.out.write(b"\0" * 4096)
            self.out.flush()
            return
        if self.mode == "huge_header" and frame.header.get("entries") is not None:
            body = struct.pack(">I", wire.MAX_HEADER + 1) + b"{}"
            self.out.write(struct.pack(">IBBI", len(body), wire.T_RESPONSE, 0, frame.req_id) + body)
            self.out.flush()
            return
        super()._send(frame)

    def serve(self) -> None:
        if self.mode != "garbage_after_hello":
            return super().serve()
        self.out.write(wire.encode_hello(self.hello()))
        self.out.write(os.urandom(1 << 16))
        self.out.flush()
        self.reader.read_hello()
        while self.reader.read_frame() is not None:
            pass


def main() -> None:
    mode, canary = sys.argv[1], sys.argv[2]
    if mode not in MODES:
        sys.exit("unknown mode %r" % mode)
    try:
        HostileServer(mode, canary).serve()
    except (EOFError, BrokenPipeError, OSError, Exception):  # noqa: BLE001 - it only has to lie
        pass


if __name__ == "__main__":
    main()
