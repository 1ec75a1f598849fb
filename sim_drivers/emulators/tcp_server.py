"""A small asyncio TCP server that tracks its client connections, so an emulator can drop them on demand
(fault injection) and shut down without leaving tasks behind."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable

from tandemscan.drivers.tasks import cancel_and_wait

log = logging.getLogger(__name__)

Handler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


class TcpService:
    """One listening socket; ``handler(reader, writer)`` runs per client. ``port`` is known after ``start``."""

    def __init__(self, handler: Handler, host: str = "127.0.0.1", port: int = 0, exclusive: bool = False,
                 refuse_second: Callable[[], bool] = lambda: False):
        """``exclusive``: one client at a time (JAKA's command port), a new one replacing the previous, or while
        ``refuse_second()`` (asked at each new client) closed at once while the previous one is still served."""
        self._handler = handler
        self.host = host
        self.port = port
        self._exclusive = exclusive
        self._refuse_second = refuse_second
        self._server: asyncio.Server | None = None
        # serving task -> (handler task, writer); the handler runs in its own task so that dropping a client
        # cancels the handler while the serving task that asyncio.start_server watches ends normally
        self._clients: dict[asyncio.Task, tuple[asyncio.Task, asyncio.StreamWriter]] = {}

    async def start(self) -> int:
        self._server = await asyncio.start_server(self._serve, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        return self.port

    @property
    def client_count(self) -> int:
        return len(self._clients)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        if self._exclusive and self._clients and self._refuse_second():
            log.info("port %d: a second client refused while the first is served", self.port)
            writer.close()
            return
        if self._exclusive:
            await self.drop_clients()
        handler = asyncio.create_task(self._handler(reader, writer))
        self._clients[task] = (handler, writer)
        try:
            await handler
        except asyncio.CancelledError:
            if not handler.cancelled():
                raise
        except (ConnectionError, OSError) as e:
            log.debug("client on port %d went away: %s", self.port, e)
        finally:
            writer.close()
            with contextlib.suppress(OSError, ConnectionError, TimeoutError):
                await asyncio.wait_for(writer.wait_closed(), 1.0)
            self._clients.pop(task, None)  # only now: drop_clients() and stop() wait for this task

    async def drop_clients(self) -> None:
        """Close every client connection at once (a disconnect fault) and wait for their handlers to end."""
        serving = list(self._clients.items())
        for _, (handler, writer) in serving:
            writer.transport.abort()  # at once, even with unsent data queued for a peer that stopped reading
            await cancel_and_wait(handler)
        for task, _ in serving:
            with contextlib.suppress(ConnectionError, OSError):
                await task

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            await self.drop_clients()
            await self._server.wait_closed()
            self._server = None
