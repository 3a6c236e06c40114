"""`collector web`: a Starlette app that shows the fleet and takes start/stop, for one browser or a few.

One task polls the collector (its status once a second, its runs every ten) through the same
Zenoh client the CLI uses and keeps the latest snapshot; every open page holds a server-sent
events stream and receives one message a second, however many readings the fleet sends.

Security: it listens on 127.0.0.1 unless told otherwise. Every request that changes something
(start, stop) must carry the page's token in ``X-BGT-Token`` and come from the page's own origin,
so another web site open in the operator's browser cannot start or stop a run. Listening on any
other address needs HTTPS (``--tls-cert``/``--tls-key``) and the access token printed at start:
the page is opened once with ``?token=...``, which sets an HTTP-only cookie.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import secrets
from collections.abc import AsyncIterator, Callable
from importlib import resources
from typing import Any

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import (
    FileResponse,
    HTMLResponse,
    JSONResponse,
    Response,
    StreamingResponse,
)
from starlette.routing import Route

from bgt_core.control_messages import CollectorStatus
from collector.client import CollectorClient
from collector.errors import CollectorError
from collector.web.plan import FloorPlan
from collector.web.position import LivePositions
from collector.web.snapshot import SILENT_S, ConsoleHistory, build_snapshot

log = logging.getLogger(__name__)

POLL_S = 1.0
RUNS_EVERY = 10  # polls
MAX_BODY = 16 * 1024
COOKIE = "bgt_console"
# The charting library, vendored in the package (collector/web/vendor/README.md): name -> type.
VENDORED = {
    "uPlot.iife.min.js": "text/javascript",
    "uPlot.min.css": "text/css",
    "uPlot.LICENSE": "text/plain",
}


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


class Console:
    """The console's state: the collector client, the latest snapshot, the open pages."""

    def __init__(
        self,
        client: CollectorClient,
        *,
        silent_s: float = SILENT_S,
        poll_s: float = POLL_S,
        token: str | None = None,
        access_token: str | None = None,
        plan: FloorPlan | None = None,
        positions: LivePositions | None = None,
    ) -> None:
        self.client = client
        self.silent_s = silent_s
        self.poll_s = poll_s
        self.token = token or secrets.token_hex(16)  # the page's token for start/stop
        self.access_token = access_token  # set when listening beyond this machine
        self.plan = plan  # the floor plan to draw the sensors on, if any
        self.positions = positions  # live position estimates from a radio map, if any
        self.history = ConsoleHistory()
        self.latest: dict[str, Any] | None = None
        self.runs: list[dict[str, Any]] = []
        self.error: str | None = None
        self._pages: set[asyncio.Queue[str]] = set()
        self._lock = asyncio.Lock()  # one Zenoh call at a time

    async def _call(self, fn: Callable[[], Any]) -> Any:
        async with self._lock:
            return await asyncio.to_thread(fn)

    async def poll_forever(self) -> None:
        n = 0
        while True:
            try:
                status = CollectorStatus.from_dict(await self._call(self.client.status))
                snap = build_snapshot(status, self.history, silent_s=self.silent_s)
                if self.positions is not None:
                    snap["positions"] = self._positions(status)
                if n % RUNS_EVERY == 0:
                    self.runs = await self._call(self.client.runs)
                self.error = None
            except (CollectorError, ValueError) as e:
                self.error = str(e)
                snap = {"error": self.error}
            snap["runs"] = self.runs[-50:]
            if self.plan is not None:
                snap["plan"] = self.plan.to_dict()
            self.latest = snap
            self._push(json.dumps(snap))
            n += 1
            await asyncio.sleep(self.poll_s)

    def _positions(self, status: CollectorStatus) -> dict[str, dict[str, Any]]:
        assert self.positions is not None
        out = self.positions.update(status)
        if self.plan is not None:
            for p in out.values():
                p["px"], p["py"], p["r_px"] = self.plan.pixels(p["x"], p["y"], p["sigma_m"])
        return out

    def _push(self, text: str) -> None:
        for q in list(self._pages):
            if q.qsize() < 5:  # a page that does not read is skipped, never waited for
                q.put_nowait(text)

    async def events(self) -> AsyncIterator[str]:
        q: asyncio.Queue[str] = asyncio.Queue()
        self._pages.add(q)
        try:
            history = {k: list(v) for k, v in self.history.points.items()}
            yield f"event: init\ndata: {json.dumps({'history': history})}\n\n"
            if self.latest is not None:
                yield f"data: {json.dumps(self.latest)}\n\n"
            while True:
                try:
                    text = await asyncio.wait_for(q.get(), 15.0)
                    yield f"data: {text}\n\n"
                except TimeoutError:
                    yield ": keep-alive\n\n"
        finally:
            self._pages.discard(q)

    async def start(self, name: str | None, notes: str | None) -> dict[str, Any]:
        return dict(await self._call(lambda: self.client.start(name, notes=notes)))

    async def stop(self) -> dict[str, Any]:
        return dict(await self._call(self.client.stop))


def _page(token: str) -> str:
    html = resources.files("collector.web").joinpath("page.html").read_text(encoding="utf-8")
    return html.replace("__BGT_TOKEN__", token)


def _authorised(request: Request, console: Console) -> bool:
    if console.access_token is None:
        return True
    return secrets.compare_digest(request.cookies.get(COOKIE, ""), console.access_token)


def _same_origin(request: Request) -> bool:
    origin = request.headers.get("origin")
    if origin is None:
        return True  # not a browser's cross-site request (curl, the tests' client)
    host = request.headers.get("host", "")
    return origin in (f"http://{host}", f"https://{host}")


def _error(message: str, status: int = 400) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status)


async def _change(request: Request, console: Console) -> Response:
    """Start or stop, for a request that proves it comes from the page."""
    if not _authorised(request, console):
        return _error("not authorised", 403)
    if not _same_origin(request):
        return _error("cross-origin request refused", 403)
    if not secrets.compare_digest(request.headers.get("x-bgt-token", ""), console.token):
        return _error("missing or wrong X-BGT-Token (reload the page)", 403)
    body = await request.body()
    if len(body) > MAX_BODY:
        return _error(f"request of {len(body)} bytes (at most {MAX_BODY})", 413)
    try:
        req = json.loads(body or b"{}")
    except ValueError:
        return _error("the request body is not JSON")
    if not isinstance(req, dict):
        return _error("the request body must be a JSON object")
    try:
        if request.url.path.endswith("/start"):
            name, notes = req.get("name") or None, req.get("notes") or None
            if not (name is None or isinstance(name, str)) or not (
                notes is None or isinstance(notes, str)
            ):
                return _error("name and notes must be text")
            reply = await console.start(name, notes)
        else:
            reply = await console.stop()
    except (CollectorError, ValueError) as e:
        return _error(str(e).splitlines()[0] if str(e) else type(e).__name__)
    return JSONResponse(reply)


async def vendored(request: Request) -> Response:
    """The charting library, from the package: nothing but the files VENDORED names."""
    name = request.path_params["name"]
    kind = VENDORED.get(name)
    if kind is None:
        return _error("no such file", 404)
    data = resources.files("collector.web").joinpath("vendor", name).read_bytes()
    return Response(data, media_type=kind, headers={"Cache-Control": "max-age=86400"})


def build_app(console: Console) -> Starlette:
    async def page(request: Request) -> Response:
        given = request.query_params.get("token")
        if console.access_token is not None and given is not None:
            if not secrets.compare_digest(given, console.access_token):
                return _error("wrong access token", 403)
            response: Response = HTMLResponse(_page(console.token))
            response.set_cookie(COOKIE, given, httponly=True, secure=True, samesite="strict")
            return response
        if not _authorised(request, console):
            return _error(
                "open this page once with ?token=<the access token collector web printed>", 403
            )
        return HTMLResponse(_page(console.token))

    async def events(request: Request) -> Response:
        if not _authorised(request, console):
            return _error("not authorised", 403)
        headers = {"Cache-Control": "no-store", "X-Accel-Buffering": "no"}
        return StreamingResponse(console.events(), media_type="text/event-stream", headers=headers)

    async def initial(request: Request) -> Response:
        if not _authorised(request, console):
            return _error("not authorised", 403)
        text = f"window.BGT_INITIAL = {json.dumps(console.latest)};\n"
        return Response(text, media_type="text/javascript", headers={"Cache-Control": "no-store"})

    async def plan_image(request: Request) -> Response:
        if not _authorised(request, console) or console.plan is None:
            return _error("no floor plan", 404)
        return FileResponse(console.plan.image, media_type="image/png")

    async def runs(request: Request) -> Response:
        if not _authorised(request, console):
            return _error("not authorised", 403)
        return JSONResponse({"runs": console.runs})

    async def change(request: Request) -> Response:
        return await _change(request, console)

    return Starlette(
        routes=[
            Route("/", page),
            Route("/events", events),
            Route("/snapshot.js", initial),
            Route("/plan.png", plan_image),
            Route("/vendor/{name}", vendored),
            Route("/api/runs", runs),
            Route("/api/start", change, methods=["POST"]),
            Route("/api/stop", change, methods=["POST"]),
        ],
        lifespan=_lifespan(console),
    )


def _lifespan(
    console: Console,
) -> Callable[[Starlette], contextlib.AbstractAsyncContextManager[None]]:
    @contextlib.asynccontextmanager
    async def lifespan(_app: Starlette) -> AsyncIterator[None]:
        task = asyncio.create_task(console.poll_forever(), name="console-poll")
        try:
            yield
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    return lifespan
