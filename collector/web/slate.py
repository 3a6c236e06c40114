"""`collector slate`: a full-screen page that shows this host's clock as a time code, for the
cameras to film at the start and the end of a capture (the annotator's ``sync.mode: slate``).

The page draws, on every refresh of the screen, one of two rows of four ArUco markers (the
annotator's ``annotator.core.sync.slate`` says what they encode); it keeps its own clock on this
host's by asking ``/time`` a few times (the fastest answer wins, as in NTP) and again every 30 s,
so a tablet or phone on the network can be the screen. It takes no input and shows nothing but
the time, so it may listen beyond this machine without a token.
"""

from __future__ import annotations

import time
from importlib import resources

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response
from starlette.routing import Route

NO_STORE = {"Cache-Control": "no-store"}


def slate_codes() -> str:
    """The marker bits the page draws (DICT_5X5_1000, as OpenCV generates them)."""
    return resources.files("collector.web").joinpath("slate_codes.json").read_text("utf-8")


def build_slate_app() -> Starlette:
    page_html = resources.files("collector.web").joinpath("slate.html").read_text("utf-8")
    codes = slate_codes()

    async def page(_request: Request) -> Response:
        return HTMLResponse(page_html, headers=NO_STORE)

    async def now(_request: Request) -> Response:
        return JSONResponse({"t_ms": time.time_ns() / 1e6}, headers=NO_STORE)

    async def code_table(_request: Request) -> Response:
        return Response(codes, media_type="application/json")

    return Starlette(
        routes=[Route("/", page), Route("/time", now), Route("/codes.json", code_table)]
    )
