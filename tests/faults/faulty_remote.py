"""A DVC remote served over HTTP on loopback that fails as real ones do: one object's bytes
flipped (a corrupting proxy or disk), cut short with a matching Content-Length (a truncated
object at the remote), or the connection dropped mid-object (a server that stops answering).
Every other request is served as `python -m http.server` serves it."""

from __future__ import annotations

import functools
import http.server
import os
import socket
import threading
from pathlib import Path

MODES = ("ok", "flip", "cut", "drop")


class FaultyRemote:
    """A read-only HTTP view of a DVC remote directory on a free loopback port; `mode` applies
    to the objects named in `targets` (their hashes), and may change while it serves."""

    def __init__(self, directory: Path, targets: set[str], mode: str = "ok") -> None:
        assert mode in MODES
        self.directory, self.targets, self.mode = directory, set(targets), mode
        remote = self

        class Handler(http.server.SimpleHTTPRequestHandler):
            def log_message(self, *args) -> None:
                pass

            def do_GET(self) -> None:  # noqa: N802 - http.server's name
                oid = "".join(self.path.rstrip("/").split("/")[-2:])
                path = Path(self.translate_path(self.path))
                if remote.mode == "ok" or oid not in remote.targets or not path.is_file():
                    return super().do_GET()
                data = path.read_bytes()
                half = data[: len(data) // 2]
                if remote.mode == "flip":
                    flipped = bytearray(data)
                    flipped[len(data) // 2] ^= 0xFF
                    body, length = bytes(flipped), len(data)
                else:
                    body, length = half, len(half if remote.mode == "cut" else data)
                self.send_response(200)
                self.send_header("Content-Type", "application/octet-stream")
                self.send_header("Content-Length", str(length))
                self.end_headers()
                self.wfile.write(body)
                if remote.mode == "drop":  # the rest never comes: the server hangs up
                    self.wfile.flush()
                    self.connection.shutdown(socket.SHUT_RDWR)
                    self.close_connection = True

        handler = functools.partial(Handler, directory=str(directory))
        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def object_hash(path: Path) -> str:
    """The DVC (3.x) object name of a file: the md5 of its bytes."""
    import hashlib

    return hashlib.md5(path.read_bytes()).hexdigest()


def cache_mismatches(cache: Path) -> list[str]:
    """The objects of a DVC cache whose bytes do not hash to their name (none, if whole)."""
    import hashlib

    bad = []
    for folder, _, files in os.walk(cache / "files" / "md5"):
        for name in files:
            path = Path(folder, name)
            oid = (path.parent.name + name).split(".")[0]
            if hashlib.md5(path.read_bytes()).hexdigest() != oid:
                bad.append(path.relative_to(cache).as_posix())
    return bad
