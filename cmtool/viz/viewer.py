"""Live Rerun viewers a run streams to: one started for it (``--spawn``), one at a gRPC URL (``--connect``), or
this process serving the recording (``--serve``: :func:`cmtool.viz.recording.served`); and a run's recording, kept
in memory and written with its files or streamed to such a viewer (:func:`run_recording`)."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path
from urllib.parse import urlsplit

import rerun as rr

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import OutputSet, temporary
from cmtool.core.outputs import os_reason
from cmtool.viz.recording import APP_IDS, GRPC_PORT, close_recording, open_recording, served

SERVING: list[rr.RecordingStream] = []  # recordings served with --serve, kept alive until the process ends
FLUSH_S = 30.0  # the longest a finished run waits for a live viewer to take the rest of the recording
PROBE_BYTES = 1 << 20


def run_recording(kind: str, rrd: Path | None, viewer: str | None) -> rr.RecordingStream:
    """A recording of one ``kind`` (a key of :data:`~cmtool.viz.recording.APP_IDS`) for ``rrd``, kept in memory
    and written with the run's files, or, with ``viewer`` ("spawn", "serve" or a gRPC URL: :func:`viewer_sink`),
    streamed to it and, when ``rrd`` is given, written by Rerun to a file beside ``rrd`` that
    :func:`finish_recording` renames into place."""
    if viewer is None:
        return open_recording(kind)
    rec = rr.RecordingStream(APP_IDS[kind])
    sinks = [viewer_sink(rec, viewer)]
    if rrd is not None:
        _room_for(rrd)
        sinks.append(rr.FileSink(str(_partial(rrd))))
    rec.set_sinks(*sinks)
    return rec


def finish_recording(rec: rr.RecordingStream, rrd: Path | None, viewer: str | None, outputs: OutputSet) -> None:
    """End a run's recording that succeeded: written to ``rrd`` with the run's ``outputs``, or, streamed to a
    ``viewer``, flushed to it (at most :data:`FLUSH_S`), kept served until the process ends ("serve") or
    disconnected, and its file renamed into place."""
    if viewer is None:
        close_recording(rec, rrd, outputs)
        return
    rec.flush(timeout_sec=FLUSH_S)
    if viewer == "serve":  # the stream owns the server: keep it until the process ends
        SERVING.append(rec)
    else:
        rec.disconnect()
    if rrd is not None:
        _partial(rrd).replace(rrd)


def drop_recording(rec: rr.RecordingStream, rrd: Path | None) -> None:
    """End a run's recording after a failure: disconnected, its partial file removed."""
    rec.disconnect()
    if rrd is not None:
        _partial(rrd).unlink(missing_ok=True)


def _partial(rrd: Path) -> Path:
    return Path(temporary(rrd, stable=True))


def _room_for(rrd: Path) -> None:
    """Refuse a recording that Rerun's own file writer would fail to write (a full disk, a size limit, no
    permission): that writer blocks for ever when a write fails, so a megabyte is written and removed first."""
    probe = _partial(rrd)
    try:
        probe.parent.mkdir(parents=True, exist_ok=True)
        with open(probe, "wb") as f:
            f.write(bytes(PROBE_BYTES))
            f.flush()
            os.fsync(f.fileno())
    except OSError as e:
        raise CmtoolError(f"cannot write {rrd}: {os_reason(e)}") from None
    finally:
        probe.unlink(missing_ok=True)


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
