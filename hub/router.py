"""The hub's embedded Zenoh router: the session every other hub service uses."""

from __future__ import annotations

import logging
from typing import Any

import zenoh

from edge.zenoh_session import router_config
from hub.errors import RouterError

log = logging.getLogger("fleetdaq.hub")


class Router:
    """Opens the router on start (edges connect to its `listen` endpoints); closes it last."""

    name = "router"

    def __init__(self, listen: list[str]) -> None:
        self.listen = listen
        self._session: Any = None

    @property
    def session(self) -> Any:
        if self._session is None:
            raise RouterError("the router is not running")
        return self._session

    def start(self) -> None:
        try:
            self._session = zenoh.open(router_config(self.listen))
        except zenoh.ZError as err:
            raise RouterError(f"cannot start the Zenoh router on {self.listen}: {err}") from err

    def stop(self) -> None:
        session, self._session = self._session, None
        if session is not None:
            session.close()

    def failure(self) -> str | None:
        return None
