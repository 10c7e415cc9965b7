"""Idempotency keys on POST: a retried request with the same key gets the stored answer.

The first answer (status < 500) to `POST path` with `Idempotency-Key: K` is stored in
SQLite with a hash of the body; a retry with the same key and body replays it without
running the request again; the same key with another body or path is a 422. The body is
hashed before the request runs, so it is spooled (memory up to 1 MiB, then a temporary
file) rather than held in memory: uploads may be hundreds of MB.
"""

from __future__ import annotations

import asyncio
import hashlib
import tempfile
import threading
import time
from typing import Any

from sqlalchemy.exc import IntegrityError

from api.db import Database, IdempotencyRecord
from api.security import send_problem

MAX_KEY_LEN = 200
MAX_STORED_BODY = 1 << 20
SPOOL_IN_MEMORY = 1 << 20  # request bodies above this go to a temporary file
REPLAY_CHUNK = 1 << 20


class IdempotencyMiddleware:
    """Pure ASGI middleware storing and replaying answers to keyed POSTs."""

    def __init__(self, app: Any, db_getter: Any) -> None:
        self.app = app
        self.db_getter = db_getter
        self._inflight: dict[str, asyncio.Lock] = {}
        self._guard = threading.Lock()

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        headers = dict(scope.get("headers", [])) if scope["type"] == "http" else {}
        key_raw = headers.get(b"idempotency-key")
        if scope["type"] != "http" or scope["method"] != "POST" or key_raw is None:
            await self.app(scope, receive, send)
            return
        key = key_raw.decode(errors="replace")
        if not 1 <= len(key) <= MAX_KEY_LEN or not key.isprintable():
            await send_problem(send, 422, "validation-error",
                               f"Idempotency-Key: expected 1..{MAX_KEY_LEN} printable characters")
            return
        with tempfile.SpooledTemporaryFile(max_size=SPOOL_IN_MEMORY) as body:
            digest = await _spool(receive, body)
            if digest is not None:
                await self._answer(scope, send, key, digest, body)

    async def _answer(self, scope: dict[str, Any], send: Any, key: str, digest: str,
                      body: Any) -> None:
        """Replay the stored answer for `key`, or run the request and store its answer."""
        db: Database = self.db_getter()
        with self._guard:
            lock = self._inflight.setdefault(key, asyncio.Lock())
        try:
            async with lock:
                stored = await asyncio.to_thread(_lookup, db, key)
                if stored is None:
                    await self._run_and_store(scope, send, db, key, digest, body)
                elif stored.body_sha256 != digest or stored.path != scope["path"]:
                    await send_problem(send, 422, "idempotency-key-reused",
                                       f"Idempotency-Key {key!r} was used for a different "
                                       f"request (POST {stored.path}); use a new key")
                else:
                    await _replay(send, stored)
        finally:
            with self._guard:
                if not lock.locked():
                    self._inflight.pop(key, None)

    async def _run_and_store(self, scope: dict[str, Any], send: Any, db: Database, key: str,
                             digest: str, body: Any) -> None:
        body.seek(0)
        finished = False

        async def replay_receive() -> dict[str, Any]:
            nonlocal finished
            if finished:
                return {"type": "http.disconnect"}
            chunk = body.read(REPLAY_CHUNK)
            finished = len(chunk) < REPLAY_CHUNK
            return {"type": "http.request", "body": chunk, "more_body": not finished}

        status = 0
        resp_headers: list[tuple[bytes, bytes]] = []
        parts: list[bytes] = []

        async def capture_send(msg: dict[str, Any]) -> None:
            nonlocal status, resp_headers
            if msg["type"] == "http.response.start":
                status, resp_headers = msg["status"], list(msg.get("headers", []))
            elif msg["type"] == "http.response.body":
                parts.append(msg.get("body", b""))
            await send(msg)

        await self.app(scope, replay_receive, capture_send)
        data = b"".join(parts)
        if 0 < status < 500 and len(data) <= MAX_STORED_BODY:
            keep = {k.decode(): v.decode() for k, v in resp_headers
                    if k.lower() in (b"content-type", b"location")}
            rec = IdempotencyRecord(key=key, method="POST", path=scope["path"],
                                    body_sha256=digest, status_code=status, headers=keep,
                                    body=data, created_at=time.time())
            await asyncio.to_thread(_store, db, rec)


async def _spool(receive: Any, body: Any) -> str | None:
    """Copy the request body into `body` (a file); its SHA-256, or None on disconnect."""
    sha = hashlib.sha256()
    while True:
        msg = await receive()
        if msg["type"] == "http.disconnect":
            return None
        chunk = msg.get("body", b"")
        sha.update(chunk)
        body.write(chunk)
        if not msg.get("more_body"):
            return sha.hexdigest()


def _lookup(db: Database, key: str) -> IdempotencyRecord | None:
    with db.session() as s:
        return s.get(IdempotencyRecord, key)


def _store(db: Database, rec: IdempotencyRecord) -> None:
    try:
        with db.session() as s:
            s.add(rec)
    except IntegrityError:
        pass  # a concurrent identical request stored it first; either answer is the same


async def _replay(send: Any, rec: IdempotencyRecord) -> None:
    headers = [(k.encode(), v.encode()) for k, v in rec.headers.items()]
    headers += [(b"content-length", str(len(rec.body)).encode()),
                (b"idempotent-replayed", b"true")]
    await send({"type": "http.response.start", "status": rec.status_code, "headers": headers})
    await send({"type": "http.response.body", "body": rec.body})

