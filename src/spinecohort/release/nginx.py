"""A local static HTTP server for a release folder: nginx on 127.0.0.1 with an access log of the bytes it
sends, for the remote-read tests and benchmark (and to try a release over HTTP before depositing it).

nginx (Debian's ``nginx-light``; scripts/install_system_deps.sh) honours Range requests, single and
suffix ranges included, as Zenodo's and S3's servers do; Python's ``http.server`` ignores them.
``max_ranges=0`` makes nginx ignore Range and send whole files (HTTP 200): a server without range support.
The server runs as one process of the calling user (no master, no daemon), all its files in ``workdir``.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from spinecohort.release.names import ReleaseError


@dataclass(frozen=True)
class Request:
    """One access-log line: the URI, the HTTP status, the body bytes sent and the Range header ("-": none)."""

    uri: str
    status: int
    nbytes: int
    range: str


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def nginx_config(root: Path, workdir: Path, port: int, max_ranges: int | None) -> str:
    """nginx.conf serving ``root`` read-only on 127.0.0.1:port; the access log records each request's URI,
    status, body bytes sent and Range header, tab-separated."""
    temp = " ".join(f"{k}_temp_path {workdir / k};" for k in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"))
    ranges = "" if max_ranges is None else f"max_ranges {int(max_ranges)};"
    return f"""daemon off;
master_process off;
worker_processes 1;
pid {workdir / "nginx.pid"};
error_log {workdir / "error.log"} warn;
events {{ worker_connections 256; }}
http {{
    log_format bytes_sent "$request_uri\\t$status\\t$body_bytes_sent\\t$http_range";
    access_log {workdir / "access.log"} bytes_sent;
    {temp}
    types {{ }}
    default_type application/octet-stream;
    server {{
        listen 127.0.0.1:{port};
        root {root};
        {ranges}
    }}
}}
"""


class LocalServer:
    """``with LocalServer(root, workdir) as srv:`` serves ``root`` at ``srv.url``; ``srv.requests()`` reads
    the access log.  Raises ReleaseError if nginx is missing or does not start."""

    def __init__(self, root, workdir, max_ranges: int | None = None, nginx: str | None = None):
        self.root, self.workdir = Path(root).resolve(), Path(workdir).resolve()
        self.max_ranges = max_ranges
        self.nginx = nginx or shutil.which("nginx") or ("/usr/sbin/nginx" if Path("/usr/sbin/nginx").exists() else None)
        if self.nginx is None:
            raise ReleaseError("nginx is not installed (scripts/install_system_deps.sh installs nginx-light)")
        self.proc = None
        self.port = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> LocalServer:
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.port = _free_port()
        conf = self.workdir / "nginx.conf"
        conf.write_text(nginx_config(self.root, self.workdir, self.port, self.max_ranges))
        err = self.workdir / "error.log"
        self.proc = subprocess.Popen(
            [self.nginx, "-e", str(err), "-p", str(self.workdir), "-c", str(conf)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                msg = self.proc.stderr.read().decode(errors="replace") + (err.read_text() if err.is_file() else "")
                raise ReleaseError(f"nginx did not start: {msg.strip()[-500:]}")
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return self
            except OSError:
                time.sleep(0.02)
        self.__exit__()
        raise ReleaseError(f"nginx did not listen on 127.0.0.1:{self.port} within 10 s")

    def __exit__(self, *exc) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc is not None:
            self.proc.stderr.close()

    def requests(self) -> list[Request]:
        """Every request served so far (nginx writes each line when the response is sent)."""
        log = self.workdir / "access.log"
        if not log.is_file():
            return []
        out = []
        for line in log.read_text().splitlines():
            uri, status, nbytes, rng = line.split("\t")
            out.append(Request(uri, int(status), int(nbytes), rng))
        return out

    def clear_log(self, settle_s: float = 0.5, timeout_s: float = 30.0) -> None:
        """Start counting afresh (nginx keeps appending to the same, truncated file), once the log has not grown
        for ``settle_s``: a response still being sent to an earlier client would otherwise be counted here."""
        import time

        log = self.workdir / "access.log"
        size, since, start = -1, time.monotonic(), time.monotonic()
        while time.monotonic() - start < timeout_s:
            now = log.stat().st_size if log.is_file() else 0
            if now != size:
                size, since = now, time.monotonic()
            elif time.monotonic() - since >= settle_s:
                break
            time.sleep(0.05)
        log.write_bytes(b"")
