"""Start a rerun viewer process bound to the loopback address: the web viewer (`--serve`) or the native one.

The Python SDK's own `serve_web_viewer` binds every interface (0.0.0.0), so the web viewer is served by the rerun
binary shipped with rerun-sdk (`rerun --serve-web --bind 127.0.0.1`), and our recording streams to it over gRPC.
"""

from __future__ import annotations

import atexit
import contextlib
import importlib.util
import logging
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

from vio.children import terminate_with_parent
from vio.errors import VioError

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
STARTUP_TIMEOUT_S = 20.0
NATIVE_SETTLE_S = 2.0
ANSI_ESCAPE = re.compile(r"\x1b\[[0-9;]*m")


@dataclass
class ViewerProcess:
    kind: str  # "web" or "native"
    process: subprocess.Popen
    grpc_port: int
    web_port: int | None  # HTTP port of the web viewer (kind "web")
    log_path: Path  # the viewer's own stdout/stderr

    @property
    def pid(self) -> int:
        return int(self.process.pid)

    @property
    def grpc_url(self) -> str:
        """Where the SDK streams to (the viewer's gRPC proxy)."""
        return f"rerun+http://{LOOPBACK}:{self.grpc_port}/proxy"

    @property
    def url(self) -> str:
        """What the user opens: the web viewer page connected to the gRPC proxy (kind "web"), else the proxy."""
        if self.web_port is None:
            return self.grpc_url
        return f"http://{LOOPBACK}:{self.web_port}/?url={quote(self.grpc_url, safe='')}"

    def stop(self, timeout_s: float = 10.0) -> None:
        """Terminate the viewer process we started (and nothing else)."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout_s)


def rerun_executable() -> str:
    """Path of the rerun binary shipped in the rerun-sdk wheel (falls back to `rerun` on PATH)."""
    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin is not None:
        exe = Path(spec.origin).parent / "rerun"
        if exe.is_file():
            return str(exe)
    found = shutil.which("rerun")
    if found is None:
        raise VioError("rerun viewer binary not found (is rerun-sdk installed?)")
    return found


def free_loopback_port() -> int:
    """A TCP port free on 127.0.0.1 right now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((LOOPBACK, 0))
        return int(s.getsockname()[1])


def _wait_listening(proc: subprocess.Popen, port: int, log_path: Path) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            lines = ANSI_ESCAPE.sub("", log_path.read_text(errors="replace")).strip().splitlines()
            last = lines[-1] if lines else "no output"
            raise VioError(f"rerun viewer exited with code {proc.returncode}: {last} (log: {log_path})")
        with contextlib.suppress(OSError), socket.create_connection((LOOPBACK, port), timeout=0.5):
            return
        time.sleep(0.1)
    proc.terminate()
    raise VioError(f"rerun viewer did not listen on {LOOPBACK}:{port} within {STARTUP_TIMEOUT_S:g} s (log: {log_path})")


def start_viewer_process(kind: str, web_port: int = 0) -> ViewerProcess:
    """Start `rerun --serve-web` (kind "web") or the native viewer (kind "native"), listening on 127.0.0.1 only.

    `web_port` 0 picks a free port. The process runs in its own session (Ctrl-C reaches only us); a web server is
    stopped when this Python process exits (atexit, and on Linux also when it is killed), a native viewer is left
    for the user to close.
    """
    grpc_port = free_loopback_port()
    args = [rerun_executable(), "--bind", LOOPBACK, "--port", str(grpc_port)]
    http_port = None
    if kind == "web":
        http_port = web_port or free_loopback_port()
        args += ["--serve-web", "--web-viewer-port", str(http_port)]
    elif kind == "native":
        if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise VioError("no display for the native rerun viewer (DISPLAY is not set); use --serve or --rrd instead")
        args += ["--expect-data-soon"]
    else:
        raise ValueError(f"unknown viewer kind {kind!r}")
    fd, name = tempfile.mkstemp(prefix=f"vio_rerun_{kind}_", suffix=".log")
    with os.fdopen(fd, "wb") as out:
        proc = subprocess.Popen(
            args,
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            preexec_fn=terminate_with_parent if kind == "web" and sys.platform.startswith("linux") else None,  # noqa: PLW1509
        )
    viewer = ViewerProcess(kind, proc, grpc_port, http_port, Path(name))
    _wait_listening(proc, grpc_port, viewer.log_path)
    if http_port is not None:
        _wait_listening(proc, http_port, viewer.log_path)
    else:  # a native viewer listens before it opens its window, which is what fails without a usable display
        time.sleep(NATIVE_SETTLE_S)
        _wait_listening(proc, grpc_port, viewer.log_path)
    if kind == "web":  # the server lives as long as this process; a native viewer window is the user's to close
        atexit.register(viewer.stop)
    log.debug("rerun %s viewer pid %d: %s", kind, proc.pid, " ".join(args))
    return viewer
