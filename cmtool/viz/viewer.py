"""Live Rerun viewers a run streams to: one started for it (``--spawn``), one at a gRPC URL (``--connect``), or
this process serving the recording (``--serve``: :func:`cmtool.viz.recording.served`)."""

from __future__ import annotations

import socket
import time
from urllib.parse import urlsplit

import rerun as rr

from cmtool.core.errors import CmtoolError
from cmtool.viz.recording import GRPC_PORT, served


def viewer_sink(rec: rr.RecordingStream, viewer: str) -> rr.GrpcSink | rr.GrpcServerSink:
    """A sink to a live viewer: "serve" serves the recording from this process; "spawn" starts a viewer; otherwise
    a gRPC URL that must be reachable."""
    if viewer == "serve":
        return served()
    spawn = viewer == "spawn"
    url = f"rerun+http://127.0.0.1:{GRPC_PORT}/proxy" if spawn else viewer
    if spawn:
        try:
            rec.spawn(port=GRPC_PORT, connect=False)
        except Exception as e:  # no viewer executable
            raise CmtoolError(f"--spawn: could not start the Rerun viewer ({e})") from None
    check_viewer(url, "--spawn" if spawn else f"--connect {viewer}", wait_s=10.0 if spawn else 2.0)
    return rr.GrpcSink(url)


def check_viewer(url: str, name: str, wait_s: float = 2.0) -> None:
    """Refuse (naming the option ``name``) a viewer URL that is not a Rerun gRPC URL, where nothing listens within
    ``wait_s``, or where a server listens that does not answer as a gRPC server does."""
    host, port = _grpc_address(url)
    deadline = time.monotonic() + wait_s
    while True:
        try:
            answers = _answers_http2(host, port)
            break
        except OSError:
            if time.monotonic() > deadline:
                why = ("the viewer did not start (is there a display?); write an .rrd and open it with `rerun "
                       "FILE.rrd` instead" if name == "--spawn" else "is a viewer running there? `rerun` starts one")
                raise CmtoolError(f"{name}: cannot reach a Rerun viewer at {url}: {why}") from None
            time.sleep(0.2)
    if not answers:
        raise CmtoolError(f"{name}: {host}:{port} accepts connections but does not answer as a Rerun viewer (gRPC) "
                          f"does")


def _grpc_address(url: str) -> tuple[str, int]:
    """(host, port) of a Rerun gRPC URL (rerun+http://HOST:PORT/proxy, port 9876 when left out)."""
    parts = urlsplit(url)
    try:
        port = parts.port or GRPC_PORT
    except ValueError:
        port = None
    if parts.scheme not in ("rerun", "rerun+http", "rerun+https") or not parts.hostname or port is None:
        raise CmtoolError(f"--connect {url}: expected a Rerun gRPC URL like rerun+http://127.0.0.1:9876/proxy "
                          f"(a port from 1 to 65535)")
    return parts.hostname, port


def _answers_http2(host: str, port: int, wait_s: float = 2.0) -> bool:
    """Whether a server at ``host:port`` answers an HTTP/2 greeting (as a gRPC server does) within ``wait_s``;
    an OSError when nothing listens there."""
    with socket.create_connection((host, port), timeout=1.0) as s:
        s.sendall(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0]))  # preface, SETTINGS
        s.settimeout(wait_s)
        try:
            return len(s.recv(9)) > 0
        except socket.timeout:
            return False
