"""``spinecohort serve`` for more than one person: one page process per browser session behind one port.

trame keeps one state per server process (its protocol class holds the server), and Kitware deploys trame
apps for many users as one process per session started by a launcher behind a proxy.  This module is that
launcher, in Python, in the same command:

* the **parent** binds the public port, loads the data once (:class:`~spinecohort.web.data.CohortData`:
  table, SSM, hex SSM, template) and forks a **zygote** before it starts any thread or event loop;
* the zygote computes the scene topology once and forks one **session** process per visitor: the data
  are the zygote's pages, shared copy-on-write, so a session costs its own page state and VTK scene
  only; each session is a trame server on a private 127.0.0.1 port;
* the parent answers ``/`` with a new session (``/s/<id>/``), proxies each session's files and websocket,
  checks the Host and the websocket's Origin, and ends sessions idle for ``idle_timeout_s`` or left by
  their browser, within at most ``max_sessions`` at once.

Every session uses the server's random access key (trame's ``authKey``), sent to the page in the address
its own origin opens; a page of another origin can neither read it nor pass the Origin check.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import errno
import logging
import os
import secrets
import signal
import socket
import sys
import time
from dataclasses import dataclass, field

from spinecohort.web.data import MAX_ZIP_MODELS, CohortData, PlatformError

log = logging.getLogger("spinecohort.serve")

LOOPBACK = ("127.0.0.1", "localhost", "::1")
#: a session whose browser closed its websocket ends after this long unless it comes back (page reload)
RECONNECT_GRACE_S = 30.0
#: a session whose page has not opened its websocket yet ends this long after the page's last request: the
#: first load fetches and compiles megabytes of client code, which on a slow link or a busy machine takes
#: far longer than a reload
FIRST_LOAD_GRACE_S = 180.0


@dataclass
class Settings:
    host: str = "127.0.0.1"
    port: int = 8080
    max_sessions: int = 8
    idle_timeout_s: float = 1800.0
    max_zip: int = MAX_ZIP_MODELS
    public_hosts: tuple[str, ...] = ()  # names the users type (a group's DNS name); loopback is always allowed
    key: str = field(default_factory=lambda: secrets.token_urlsafe(24))

    def allowed_hosts(self) -> set[str]:
        names = {*LOOPBACK, *self.public_hosts}
        if self.host in ("0.0.0.0", "::", ""):
            names |= {socket.gethostname(), socket.getfqdn()}
        else:
            names.add(self.host)
        return {n.lower() for n in names}


def bind(host: str, port: int) -> socket.socket:
    """The listening socket, bound before anything slow: a port in use is one clear error, at once."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise PlatformError(
                f"port {port} on {host} is already in use (another spinecohort serve?); choose one with --port"
            ) from None
        raise PlatformError(f"cannot listen on {host}:{port}: {exc.strerror}") from None
    sock.listen(128)
    sock.setblocking(False)
    return sock


def host_of(header: str | None) -> str:
    """``example.org:8080`` -> ``example.org``; ``[::1]:8080`` -> ``::1``."""
    h = (header or "").strip().lower()
    if h.startswith("["):
        return h[1 : h.find("]")] if "]" in h else h
    return h.rsplit(":", 1)[0] if h.count(":") == 1 else h


def origin_refusal(origin: str | None, host_header: str | None, allowed: set[str]) -> str | None:
    """Why a websocket from ``origin`` to ``host_header`` is refused, or None: the Origin must be this
    server as the page addressed it (scheme http/https, same host and port), and that host one of
    ``allowed`` (which stops a foreign DNS name pointed at this machine)."""
    if host_of(host_header) not in allowed:
        return f"Host {str(host_header)[:60]!r} is not one this server answers to"
    if not origin:
        return "no Origin header"
    o = origin.strip().lower()
    for scheme in ("http://", "https://"):
        if o.startswith(scheme) and o[len(scheme) :] == str(host_header).strip().lower():
            return None
    return f"Origin {origin[:60]!r} is not this server ({host_header})"


# ----------------------------------------------------------------------------------------------- sessions
def trame_argv(key: str) -> list[str]:
    """trame's command-line options of a session.  The key is one token: a URL-safe random key starts with '-'
    one time in 64, and as a separate word argparse would take it for an option and end the session."""
    return [f"--authKey={key}"]


def run_session(data: CohortData, port: int, key: str, max_zip: int, topology: dict, name: str) -> None:
    """One browser session: the platform's page as a trame server on 127.0.0.1:``port`` (blocking)."""
    from trame.app import get_server

    from spinecohort.web import guard
    from spinecohort.web.app import Platform

    sys.argv = [sys.argv[0], *trame_argv(key)]  # trame reads its options (here: the access key) from argv
    server = get_server("spinecohort", client_type="vue3")
    page = Platform(data, server, max_zip=max_zip, topology=topology)
    guard.install(server, guard.state_rules(page), on_refuse=lambda why: page.error(PlatformError(f"refused: {why}")))
    log.info("session %s: page ready on 127.0.0.1:%d", name, port)
    server.start(host="127.0.0.1", port=port, open_browser=False, timeout=0, show_connection_info=False)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _die_with_parent() -> None:
    """Linux: SIGTERM this process when its parent (the zygote) ends, so no session outlives the server."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def zygote_main(conn, data: CohortData, settings: Settings) -> None:
    """The zygote's loop: on each request fork a session on a free port and answer (pid, port)."""
    from spinecohort.web.scene import model_topology

    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # sessions are reaped by the kernel
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the parent, which closes the pipe
    topology = model_topology(data.template)
    import trame.app  # noqa: F401  (imported once here, shared by every session)
    import trame.widgets.vtk  # noqa: F401
    import trame.widgets.vuetify3  # noqa: F401

    conn.send(("ready", os.getpid()))
    while True:
        try:
            name = conn.recv()
        except (EOFError, OSError):
            os._exit(0)
        port = _free_port()
        pid = os.fork()
        if pid == 0:
            conn.close()
            signal.signal(signal.SIGCHLD, signal.SIG_DFL)
            signal.signal(signal.SIGINT, signal.default_int_handler)
            _die_with_parent()
            code = 0
            try:
                run_session(data, port, settings.key, settings.max_zip, topology, name)
            except BaseException as exc:  # noqa: BLE001  (one line, then the session process ends)
                if not isinstance(exc, (KeyboardInterrupt, SystemExit)):
                    log.error("session %s failed: %s: %s", name, type(exc).__name__, exc)
                    code = 1
            os._exit(code)
        conn.send((pid, port))


@dataclass
class Session:
    name: str
    pid: int
    port: int
    created: float
    last_active: float
    n_ws: int = 0
    assigned: bool = False
    connected: bool = False  # its page has opened a websocket at least once


def ending(sess: Session, now: float, idle_timeout_s: float) -> str | None:
    """Why the reaper ends ``sess`` at time ``now`` (s), or None: idle for ``idle_timeout_s``, or no websocket
    for `RECONNECT_GRACE_S` once its page has connected (`FIRST_LOAD_GRACE_S` before), each counted from its
    last request and bounded by the idle timeout."""
    quiet_s = now - sess.last_active
    if quiet_s > idle_timeout_s:
        return f"idle for {idle_timeout_s:g} s"
    grace_s = min(RECONNECT_GRACE_S if sess.connected else FIRST_LOAD_GRACE_S, idle_timeout_s)
    if sess.n_ws == 0 and quiet_s > grace_s:
        return "its browser left" if sess.connected else "its page never connected"
    return None


class Launcher:
    """The public side: new sessions, the proxy to them, the Host/Origin checks and the session bounds."""

    def __init__(self, settings: Settings, conn, zygote_pid: int):
        import aiohttp

        self.s, self.conn, self.zygote_pid = settings, conn, zygote_pid
        self.allowed = settings.allowed_hosts()
        self.sessions: dict[str, Session] = {}
        self.spare: Session | None = None
        self.refilling: asyncio.Task | None = None
        self._spawn_lock = asyncio.Lock()
        self.http = aiohttp.ClientSession(auto_decompress=False)

    # ---------------------------------------------------------------------- processes
    async def _spawn(self) -> Session:
        import aiohttp

        async with self._spawn_lock:
            name = secrets.token_hex(10)  # lower case: the client lowercases its websocket address
            loop = asyncio.get_running_loop()
            await loop.run_in_executor(None, self.conn.send, name)
            pid, port = await loop.run_in_executor(None, self.conn.recv)
        sess = Session(name, pid, port, time.time(), time.time())
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 120:
            try:
                async with self.http.get(f"http://127.0.0.1:{port}/index.html") as r:
                    if r.status == 200:
                        return sess
            except aiohttp.ClientError:
                pass
            if not _alive(pid):
                break
            await asyncio.sleep(0.1)
        self._kill(sess, "did not start")
        raise PlatformError("a new session did not start; see the server's log")

    def _kill(self, sess: Session, why: str) -> None:
        self.sessions.pop(sess.name, None)
        with contextlib.suppress(ProcessLookupError):
            os.kill(sess.pid, signal.SIGTERM)
        log.info("session %s ended (%s); %d of %d in use", sess.name[:6], why, len(self.sessions), self.s.max_sessions)

    async def _refill(self) -> None:
        try:
            self.spare = await self._spawn()
        except PlatformError as exc:
            log.error("%s", exc)

    def refill(self) -> None:
        """Start the next session ahead of its visitor (a session takes seconds to build its page)."""
        if self.refilling is None or self.refilling.done():
            self.refilling = asyncio.get_running_loop().create_task(self._refill())

    async def reaper(self) -> None:
        """End sessions idle for ``idle_timeout_s`` or whose browser left (no websocket for the grace)."""
        while True:
            await asyncio.sleep(1.0)
            now = time.time()
            for sess in list(self.sessions.values()):
                why = ending(sess, now, self.s.idle_timeout_s)
                if why is None and not _alive(sess.pid):
                    why = "its process stopped"
                if why is not None:
                    self._kill(sess, why)

    # ---------------------------------------------------------------------- HTTP
    def _host_ok(self, request) -> bool:
        if host_of(request.host) in self.allowed:
            return True
        log.warning(
            "refused %s %s: Host %r is not one this server answers to", request.method, request.path, request.host
        )
        return False

    async def new_session(self, request):
        from aiohttp import web

        if not self._host_ok(request):
            raise web.HTTPForbidden(text="this server does not answer to that host name\n")
        if len(self.sessions) >= self.s.max_sessions:
            log.warning("refused a new session: all %d sessions in use", self.s.max_sessions)
            return web.Response(
                status=503,
                content_type="text/html",
                text=f"<p>All {self.s.max_sessions} sessions of this spinecohort server are in use. Try again in a "
                f"few minutes: a session ends {self.s.idle_timeout_s / 60:g} min after its last action, or "
                f"{RECONNECT_GRACE_S:g} s after its browser tab closed.</p>",
            )
        if self.spare is None and self.refilling is not None and not self.refilling.done():
            await asyncio.shield(self.refilling)  # the spare is being built: take it
        sess, self.spare = self.spare, None
        if sess is None or not _alive(sess.pid):
            sess = await self._spawn()
        sess.assigned, sess.last_active = True, time.time()
        self.sessions[sess.name] = sess
        self.refill()
        log.info(
            "session %s started (pid %d); %d of %d in use",
            sess.name[:6],
            sess.pid,
            len(self.sessions),
            self.s.max_sessions,
        )
        raise web.HTTPFound(self.page_url(sess))

    def page_url(self, sess: Session) -> str:
        """The session's page with its websocket address (the client puts the browser's host in place of
        USE_HOST and ws/wss for http/https) and the access key; the client removes both from the address bar."""
        return f"/s/{sess.name}/index.html?sessionURL=ws://USE_HOST/s/{sess.name}/ws&secret={self.s.key}"

    async def status(self, request):
        from aiohttp import web

        if not self._host_ok(request):
            raise web.HTTPForbidden(text="this server does not answer to that host name\n")
        return web.json_response({"sessions": len(self.sessions), "max_sessions": self.s.max_sessions})

    async def files(self, request):
        """A session's page files, fetched from its process (the index gets the access key)."""
        from aiohttp import web

        if not self._host_ok(request):
            raise web.HTTPForbidden(text="this server does not answer to that host name\n")
        sess = self.sessions.get(request.match_info["sid"])
        tail = request.match_info["tail"]
        if sess is None:
            if tail in ("", "index.html"):
                raise web.HTTPFound("/")  # an ended session: a new one
            raise web.HTTPNotFound(text="no such session\n")
        if tail in ("", "index.html") and "secret" not in request.query:
            raise web.HTTPFound(self.page_url(sess))  # a reload
        sess.last_active = time.time()
        async with self.http.get(f"http://127.0.0.1:{sess.port}/{tail}", params=request.query) as r:
            body = await r.read()
            headers = {
                k: v
                for k, v in r.headers.items()
                if k.lower() in ("content-type", "content-encoding", "cache-control", "etag", "last-modified")
            }
            return web.Response(status=r.status, body=body, headers=headers)

    async def websocket(self, request):
        """The session's websocket, proxied message by message after the Origin check."""
        import aiohttp
        from aiohttp import web

        sess = self.sessions.get(request.match_info["sid"])
        if sess is None:
            raise web.HTTPNotFound(text="no such session\n")
        ws_upgrade = request.headers.get("Upgrade", "").lower() == "websocket"
        if not ws_upgrade:
            raise web.HTTPBadRequest(text="this address is the page's websocket; open the page instead\n")
        why = origin_refusal(request.headers.get("Origin"), request.host, self.allowed)
        if why:
            log.warning("refused a websocket to session %s: %s", sess.name[:6], why)
            raise web.HTTPForbidden(text="websocket refused: the page's origin is not this server\n")
        browser = web.WebSocketResponse(max_msg_size=0, compress=True)
        await browser.prepare(request)
        sess.n_ws += 1
        sess.connected = True
        sess.last_active = time.time()
        try:
            async with self.http.ws_connect(f"ws://127.0.0.1:{sess.port}/ws", max_msg_size=0) as worker:

                async def up():
                    async for msg in browser:
                        sess.last_active = time.time()
                        if msg.type == aiohttp.WSMsgType.BINARY:
                            await worker.send_bytes(msg.data)
                        elif msg.type == aiohttp.WSMsgType.TEXT:
                            await worker.send_str(msg.data)
                    await worker.close()

                async def down():
                    async for msg in worker:
                        if msg.type == aiohttp.WSMsgType.BINARY:
                            await browser.send_bytes(msg.data)
                        elif msg.type == aiohttp.WSMsgType.TEXT:
                            await browser.send_str(msg.data)
                    await browser.close()

                await asyncio.gather(up(), down(), return_exceptions=True)
        except (aiohttp.ClientError, ConnectionError) as exc:
            log.warning("session %s: websocket closed: %s", sess.name[:6], exc)
        finally:
            sess.n_ws -= 1
            sess.last_active = time.time()
        return browser

    def app(self):
        from aiohttp import web

        app = web.Application()
        app.router.add_get("/", self.new_session)
        app.router.add_get("/status", self.status)
        app.router.add_get("/s/{sid}/ws", self.websocket)
        app.router.add_get("/s/{sid}/{tail:.*}", self.files)
        return app

    def stop_all(self) -> None:
        for sess in [*self.sessions.values(), *([self.spare] if self.spare else [])]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(sess.pid, signal.SIGTERM)
        self.sessions.clear()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # a zombie is not alive
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


async def _run(settings: Settings, conn, zygote_pid: int, sock: socket.socket) -> None:
    from aiohttp import web

    launcher = Launcher(settings, conn, zygote_pid)
    runner = web.AppRunner(launcher.app(), handle_signals=False, access_log=None)
    await runner.setup()
    await web.SockSite(runner, sock).start()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    reaper = loop.create_task(launcher.reaper())
    launcher.refill()  # the first visitor finds a session ready
    await stop.wait()
    reaper.cancel()
    launcher.stop_all()
    await launcher.http.close()
    await runner.cleanup()


def serve(data: CohortData, settings: Settings, sock: socket.socket | None = None) -> None:
    """Serve ``data`` (any source: a results folder, a release) to up to ``settings.max_sessions`` browser
    sessions at once (blocking until SIGINT or SIGTERM)."""
    import multiprocessing

    sock = sock or bind(settings.host, settings.port)
    parent, child = multiprocessing.Pipe()
    pid = os.fork()  # before any thread or event loop of this process
    if pid == 0:
        parent.close()
        sock.close()
        code = 0
        try:
            zygote_main(child, data, settings)
        except BaseException as exc:  # noqa: BLE001
            log.error("the session starter failed: %s: %s", type(exc).__name__, exc)
            code = 1
        os._exit(code)
    child.close()
    what, _ = parent.recv()
    assert what == "ready"
    try:
        asyncio.run(_run(settings, parent, pid, sock))
    finally:
        parent.close()  # the zygote sees EOF and ends; its sessions follow (parent-death signal)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, 0)
