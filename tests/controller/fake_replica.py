"""A stand-in service replica for broker tests: configurable delay and failures, real HTTP.

Environment: ``FAKE_NAME``, ``FAKE_DELAY_MS`` (per task), ``FAKE_FAIL`` = ``none`` | ``500``
(every task answers 500) | ``hang`` (tasks never finish), ``FAKE_FAIL_FIRST`` (the first N tasks
answer 500, then it recovers).
"""

from __future__ import annotations

import asyncio
import os

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

app = FastAPI()
_state = {"in_flight": 0, "served": 0}


@app.get("/health")
async def health() -> dict[str, object]:
    return {"status": "ok", "in_flight": _state["in_flight"], "name": os.environ.get("FAKE_NAME")}


@app.post("/work")
async def work(request: Request) -> JSONResponse:
    _state["in_flight"] += 1
    try:
        _state["served"] += 1
        fail = os.environ.get("FAKE_FAIL", "none")
        if fail == "hang":
            await asyncio.sleep(3600)
        if fail == "500" or _state["served"] <= int(os.environ.get("FAKE_FAIL_FIRST", "0")):
            return JSONResponse({"error": "boom"}, status_code=500)
        await asyncio.sleep(float(os.environ.get("FAKE_DELAY_MS", "0")) / 1000.0)
        # The client's port tells the connections apart.
        port = str(request.client.port) if request.client is not None else ""
        return JSONResponse(
            {"replica": os.environ.get("FAKE_NAME")}, headers={"X-Client-Port": port}
        )
    finally:
        _state["in_flight"] -= 1
