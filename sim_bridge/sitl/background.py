"""A SitlServer on its own thread and event loop, for tests and embedding."""
from __future__ import annotations

import asyncio
import threading

from sim_bridge.sitl.config import SitlConfig
from sim_bridge.sitl.server import SitlServer


class BackgroundSitl:
    """Run a SitlServer on its own thread and event loop (tests, embedding)."""

    def __init__(self, cfg: SitlConfig, **kwargs):
        self.server = SitlServer(cfg, **kwargs)
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, name="sitl", daemon=True)

    def _main(self) -> None:
        try:
            asyncio.run(self.server.run(on_ready=lambda s: self._ready.set()))
        except BaseException as exc:  # surfaced by start()/stop()
            self._error = exc
            self._ready.set()

    def start(self, timeout_s: float = 30.0) -> SitlServer:
        self._thread.start()
        if not self._ready.wait(timeout_s) or self._error is not None:
            raise RuntimeError(f"SITL did not start: {self._error!r}")
        return self.server

    def stop(self, timeout_s: float = 10.0) -> None:
        self.server.request_stop()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            raise RuntimeError("SITL thread did not stop")

    def __enter__(self) -> SitlServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
