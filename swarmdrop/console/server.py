"""The console's web server (aiohttp): the page, its assets and one websocket per page.

Routes: ``/`` the page, ``/static/<file>`` its assets (only the files shipped in
swarmdrop/console/static/), ``/ws`` the websocket (swarmdrop.console.protocol),
``/api/meta`` and ``/api/status`` the same JSON the websocket carries (for scripts).

Every page gets, per frame, one binary message with the latest snapshot; a page that reads
slower than frames come gets the newest frame only (older ones are replaced, never queued:
`frames_dropped`). JSON messages to a page are queued up to `TEXT_QUEUE` (the oldest
dropped first). What a page sends is parsed with a size limit and a rate limit, and
anything malformed is answered with an error, never raised.

Security (docs/console.md): the server binds 127.0.0.1 unless told otherwise; it answers
only requests whose Host header names the address it serves (no DNS rebinding) and opens a
websocket only for a page of its own origin (another site open in the operator's browser
cannot send commands); every response forbids framing and loads nothing from elsewhere.
"""
from __future__ import annotations

import asyncio
import collections
import ipaddress
import json
import math
import time
from importlib import resources
from typing import Any

from aiohttp import WSMsgType, web

from swarmdrop.console.protocol import MAX_CLIENT_MESSAGE, pack_frame

STATIC_FILES = {"index.html": "text/html", "console.js": "text/javascript", "console.css": "text/css",
                "geo.js": "text/javascript"}
TEXT_QUEUE = 64
REQUESTS_PER_S = 20.0


def json_text(obj: Any) -> str:
    """Strict JSON (JavaScript's JSON.parse refuses NaN): non-finite numbers become null."""
    try:
        return json.dumps(obj, allow_nan=False, separators=(",", ":"))
    except ValueError:
        return json.dumps(_finite(obj), allow_nan=False, separators=(",", ":"))


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class _Page:
    """One connected page: the newest frame and status for it, and its queued JSON."""

    def __init__(self, ws: web.WebSocketResponse):
        self.ws = ws
        self.frame: bytes | None = None
        self.status: str | None = None
        self.texts: collections.deque[str] = collections.deque(maxlen=TEXT_QUEUE)
        self.wake = asyncio.Event()
        self.frames_sent = self.frames_dropped = 0
        self.tokens = REQUESTS_PER_S
        self.tokens_at = time.monotonic()

    def allow_request(self) -> bool:
        now = time.monotonic()
        self.tokens = min(REQUESTS_PER_S, self.tokens + (now - self.tokens_at) * REQUESTS_PER_S)
        self.tokens_at = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


class ConsoleServer:
    """Serves one feed (swarmdrop.console.feeds) to any number of pages.

    Args:
        feed: a LiveFeed or a ReplayFeed.
        host, port: where to listen (port 0: an ephemeral one; `port` holds it once started).
        frame_rate: frames per second to each page.
        status_rate: status messages per second.
    """

    def __init__(self, feed, host: str = "127.0.0.1", port: int = 8765, frame_rate: float = 20.0,
                 status_rate: float = 2.0):
        self.feed = feed
        self.host, self.port = host, port
        self.frame_rate, self.status_rate = frame_rate, status_rate
        self.pages: set[_Page] = set()
        self._runner: web.AppRunner | None = None
        self._tasks: list[asyncio.Task] = []
        self._seq = 0
        self._meta = ""
        self._status = ""
        self._status_at = -math.inf
        """Loop time the status text was made, s (_set_status)."""
        self.bad_requests = 0
        self.refused_origin = 0
        self.frame_errors = 0

    # ---- HTTP ----------------------------------------------------------------------
    def app(self) -> web.Application:
        app = web.Application(middlewares=[self._guard], client_max_size=MAX_CLIENT_MESSAGE)
        app.router.add_get("/", self._index)
        app.router.add_get("/static/{name}", self._static)
        app.router.add_get("/ws", self._websocket)
        app.router.add_get("/api/meta", self._api_meta)
        app.router.add_get("/api/status", self._api_status)
        app.router.add_get("/favicon.ico", self._no_icon)
        return app

    def _allowed_hosts(self) -> set[str] | None:
        """Host header values this server answers (None: any, when bound to a non-loopback address)."""
        if not _is_loopback(self.host):
            return None
        return {f"{h}:{self.port}" for h in ("127.0.0.1", "localhost", "[::1]", self.host)}

    @web.middleware
    async def _guard(self, request: web.Request, handler):
        allowed = self._allowed_hosts()
        if allowed is not None and request.host not in allowed:
            return web.Response(status=421, text="wrong Host for this console\n")
        resp = await handler(request)
        if not isinstance(resp, web.WebSocketResponse):
            ws_url = f"ws://{request.host}"
            resp.headers["Content-Security-Policy"] = (
                f"default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
                f"connect-src 'self' {ws_url}; frame-ancestors 'none'; base-uri 'none'; form-action 'none'")
            resp.headers["X-Content-Type-Options"] = "nosniff"
            resp.headers["X-Frame-Options"] = "DENY"
            resp.headers["Referrer-Policy"] = "no-referrer"
            resp.headers["Cache-Control"] = "no-store"
        return resp

    def _asset(self, name: str) -> bytes:
        return (resources.files("swarmdrop.console") / "static" / name).read_bytes()

    async def _index(self, request: web.Request) -> web.Response:
        return web.Response(body=self._asset("index.html"), content_type="text/html", charset="utf-8")

    async def _static(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        kind = STATIC_FILES.get(name)
        if kind is None:
            raise web.HTTPNotFound()
        return web.Response(body=self._asset(name), content_type=kind, charset="utf-8")

    async def _no_icon(self, request: web.Request) -> web.Response:
        return web.Response(status=204)

    async def _api_meta(self, request: web.Request) -> web.Response:
        return web.Response(text=json_text(self.feed.meta()), content_type="application/json")

    async def _api_status(self, request: web.Request) -> web.Response:
        # Made afresh at most once a status period: the frame loop only refreshes it while a
        # page is open, and a script polling health must not read a frozen snapshot as news.
        if asyncio.get_running_loop().time() - self._status_at >= 1.0 / self.status_rate:
            snap, _ = self.feed.snapshot()
            self._set_status(snap)
        return web.Response(text=self._status, content_type="application/json")

    def _set_status(self, snap) -> None:
        self._status = json_text(self.feed.status(snap))
        self._status_at = asyncio.get_running_loop().time()

    # ---- websocket -----------------------------------------------------------------
    def _same_origin(self, request: web.Request) -> bool:
        origin = request.headers.get("Origin")
        if origin is None:
            return False
        scheme, _, rest = origin.partition("://")
        return scheme in ("http", "https") and rest.rstrip("/") == request.host

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        if not self._same_origin(request):
            self.refused_origin += 1
            return web.Response(status=403, text="websocket only from this console's own page\n")
        ws = web.WebSocketResponse(compress=False, max_msg_size=MAX_CLIENT_MESSAGE, heartbeat=10.0)
        await ws.prepare(request)
        page = _Page(ws)
        self.pages.add(page)
        page.texts.append(self._meta or json_text(self.feed.meta()))
        page.wake.set()
        sender = asyncio.create_task(self._sender(page))
        try:
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    await self._on_request(page, msg.data)
                elif msg.type in (WSMsgType.BINARY,):
                    self.bad_requests += 1
                elif msg.type == WSMsgType.ERROR:
                    break
        finally:
            self.pages.discard(page)
            sender.cancel()
            try:
                await sender
            except (asyncio.CancelledError, Exception):
                pass
        return ws

    async def _on_request(self, page: _Page, text: str) -> None:
        rid = None
        try:
            msg = json.loads(text)
            if not isinstance(msg, dict):
                raise ValueError("not an object")
            rid = msg.get("id")
            if not isinstance(rid, (int, str, type(None))) or (isinstance(rid, str) and len(rid) > 64):
                rid = None
            if not page.allow_request():
                answer = {"ok": False, "text": "too many requests"}
            else:
                answer = await self.feed.request(msg)
        except (ValueError, TypeError, RecursionError):
            self.bad_requests += 1
            answer = {"ok": False, "text": "not a request"}
        except Exception as err:  # a bug in a handler must not end the page's connection
            self.bad_requests += 1
            answer = {"ok": False, "text": f"error: {type(err).__name__}"}
        page.texts.append(json_text({"type": "result", "id": rid, **answer}))
        page.wake.set()
        if answer.get("ok") and "replay" in answer:  # every page follows the playhead
            self._push_status(now=True)

    async def _sender(self, page: _Page) -> None:
        ws = page.ws
        while not ws.closed:
            await page.wake.wait()
            page.wake.clear()
            while page.texts:
                await ws.send_str(page.texts.popleft())
            if page.status is not None:
                s, page.status = page.status, None
                await ws.send_str(s)
            if page.frame is not None:
                f, page.frame = page.frame, None
                await ws.send_bytes(f)
                page.frames_sent += 1

    # ---- the loops -----------------------------------------------------------------
    def _push_status(self, now: bool = False) -> None:
        snap, _ = self.feed.snapshot()
        self._set_status(snap)
        for p in self.pages:
            p.status = self._status
            p.wake.set()

    async def _frames(self) -> None:
        period = 1.0 / self.frame_rate
        status_every = max(1, round(self.frame_rate / self.status_rate))
        loop = asyncio.get_running_loop()
        next_at = loop.time()
        k = 0
        while True:
            try:
                snap, flags = self.feed.snapshot()
                if self.pages:
                    self._seq += 1
                    frame = pack_frame(snap, self._seq, flags)
                    for p in self.pages:
                        if p.frame is not None:
                            p.frames_dropped += 1
                        p.frame = frame
                        p.wake.set()
                if k % status_every == 0:
                    meta = json_text(self.feed.meta())
                    if meta != self._meta:
                        self._meta = meta
                        for p in self.pages:
                            p.texts.append(meta)
                            p.wake.set()
                    if self.pages:
                        self._set_status(snap)
                        for p in self.pages:
                            p.status = self._status
                            p.wake.set()
            except Exception:  # a frame that cannot be made is skipped, never fatal
                self.frame_errors += 1
            k += 1
            next_at += period
            delay = next_at - loop.time()
            if delay < -1.0:  # far behind (a stalled machine): do not burst
                next_at = loop.time()
                delay = 0.0
            await asyncio.sleep(max(0.0, delay))

    async def start(self) -> str:
        """Listen; returns the page's URL.

        Raises:
            OSError: the port cannot be bound (in use, no such address).
        """
        loop = asyncio.get_running_loop()
        self._runner = web.AppRunner(self.app(), access_log=None, handle_signals=False, shutdown_timeout=1.0)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port)
        await site.start()
        server = getattr(site, "_server", None)
        if self.port == 0 and server is not None and server.sockets:
            self.port = server.sockets[0].getsockname()[1]
        self.feed.start(loop)
        self._meta = json_text(self.feed.meta())
        self._tasks.append(asyncio.create_task(self._frames()))
        return self.url

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            try:
                await t
            except (asyncio.CancelledError, Exception):
                pass
        for p in list(self.pages):
            await p.ws.close()
        if self._runner is not None:
            await self._runner.cleanup()
        self.feed.close(asyncio.get_running_loop())
