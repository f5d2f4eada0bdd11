"""The viewer's browser clients: frame acknowledgements (the backpressure that sends each
page the mesh updates it can draw), notifications, cameras and mouse drags.

viser is an optional dependency (``fem3d[view]``); this module imports its message types
where it needs them, so that ``fem3d`` can register ``fem3d view`` without viser.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from typing import Any

__all__ = ["ACK_TIMEOUT", "FrameAcks", "Notifications", "drag_handler", "set_client_camera"]

#: A mesh update waits until every page has processed the previous one (frame
#: acknowledgement), but never longer than this (seconds): a stalled tab cannot freeze the
#: others for good.
ACK_TIMEOUT = 1.0
_ACK_KEY = "fem3d-frame-ack"


class FrameAcks:
    """Frame acknowledgements of the connected pages.

    Parameters
    ----------
    lock : threading.Lock
        The viewer's shared-state lock (guards every attribute).
    wake : threading.Event
        Set when a page acknowledges (the simulation thread may send the next update).

    Attributes
    ----------
    clients : dict
        Client id -> [last seq sent, last seq acked, time sent].
    acked : int
        Mesh updates the pages acknowledged.
    held_back : int
        Mesh updates not sent because a page had not processed the previous one.
    """

    def __init__(self, lock: threading.Lock, wake: threading.Event) -> None:
        self._lock = lock
        self._wake = wake
        self.clients: dict[int, list[float]] = {}
        self._seq = 0
        self.acked = 0
        self.held_back = 0

    def __len__(self) -> int:
        return len(self.clients)

    def register(self, client: Any) -> None:
        """Listen for the page's frame acknowledgements (see :meth:`request`)."""
        try:
            from viser import _messages as vm  # optional dependency (fem3d[view])

            conn = client._websock_connection
        except (ImportError, AttributeError):  # pragma: no cover - another viser
            return
        cid = int(client.client_id)

        def got(_client_id: int, message: Any) -> None:
            uid = str(getattr(message, "request_uuid", ""))
            if not uid.startswith("fem3d-ack-"):
                return
            seq = int(uid.rsplit("-", 1)[1])
            with self._lock:
                st = self.clients.get(cid)
                if st is not None and seq > st[1]:
                    st[1] = seq
                    self.acked += 1
            self._wake.set()

        conn.register_handler(vm.LocalStorageGetItemResponseMessage, got)
        with self._lock:
            self.clients[cid] = [0, 0, 0.0]

    def drop(self, client_id: int) -> None:
        """Forget a client that left (the caller holds the lock)."""
        self.clients.pop(client_id, None)

    def busy(self, now: float) -> bool:
        """True while some page has not yet processed the last mesh update (for at most
        :data:`ACK_TIMEOUT` seconds)."""
        with self._lock:
            return any(st[1] < st[0] and now - st[2] < ACK_TIMEOUT
                       for st in self.clients.values())

    def hold_back(self) -> None:
        """Count a mesh update not sent (a page is still busy with the last one)."""
        with self._lock:
            self.held_back += 1

    def request(self, clients: Iterable[Any], now: float) -> None:
        """Ask every page to answer once it has processed the messages sent so far.

        The request is a localStorage read, which viser's client answers from the page's
        main thread (the one that draws): a page busy drawing answers late, and the next
        mesh update waits for the answer. This is the viewer's backpressure: the pages get
        the updates they can draw instead of a queue of stale ones.
        """
        try:
            from viser import _messages as vm  # optional dependency (fem3d[view])
        except ImportError:  # pragma: no cover
            return
        self._seq += 1
        seq = self._seq
        for client in clients:
            cid = int(client.client_id)
            with self._lock:
                st = self.clients.get(cid)
                if st is None:
                    continue
                st[0], st[2] = seq, now
            try:
                client._websock_connection.queue_message(
                    vm.LocalStorageGetItemRequestMessage(key=_ACK_KEY,
                                                         request_uuid=f"fem3d-ack-{seq}")
                )
            except Exception:  # noqa: BLE001 - a closing client
                with self._lock:
                    self.clients.pop(cid, None)


class Notifications:
    """The error notifications shown on the pages (removed on a reset or a scene switch).

    Parameters
    ----------
    lock : threading.Lock
        Guards the handles (a client that connects is notified from viser's thread).
    """

    def __init__(self, lock: threading.Lock) -> None:
        self._lock = lock
        self._handles: list[Any] = []

    def notify_client(self, client: Any, title: str, body: str, color: str) -> None:
        """A notification on one page, kept until :meth:`clear`."""
        try:
            h = client.add_notification(title, body, color=color)
        except Exception:  # noqa: BLE001 - a closing client must not kill the sim thread
            return
        with self._lock:  # also called from viser's thread (client connect)
            self._handles.append(h)

    @staticmethod
    def notify_all(clients: Iterable[Any], title: str, body: str, color: str = "blue",
                   seconds: float = 6.0) -> None:
        """A notification on every page that closes itself after ``seconds``."""
        for client in clients:
            try:
                client.add_notification(title, body, color=color, auto_close_seconds=seconds)
            except Exception:  # noqa: BLE001
                pass

    def clear(self) -> None:
        """Remove the kept notifications."""
        with self._lock:
            handles, self._handles = self._handles, []
        for h in handles:
            try:
                h.remove()
            except Exception:  # noqa: BLE001 - the client may be gone
                pass


def set_client_camera(client: Any, cam: dict[str, Any]) -> None:
    """Point ``client``'s camera as ``cam`` (:func:`~fem3d.app.viewer.logic.camera_for_points`)."""
    client.camera.near = float(cam["near"])
    client.camera.far = float(cam["far"])
    client.camera.position = tuple(cam["position"])
    client.camera.look_at = tuple(cam["look_at"])


def drag_handler(
    begin: Callable[..., None], move: Callable[..., None], end: Callable[..., None]
) -> Callable[[Any], Any]:
    """The mesh's left-button drag callback: a drag's start, moves and release become
    ``begin(start, end, owner=...)``, ``move(end, owner=...)``, ``end(owner=...)`` of the
    dragging client (so two clients dragging at once cannot end each other's drag)."""

    async def _on_drag(event: Any) -> None:
        owner = getattr(event, "client_id", None)
        if event.phase == "start":
            begin(event.start_position, event.end_position, owner=owner)
        elif event.phase == "update":
            move(event.end_position, owner=owner)
        else:
            end(owner=owner)

    return _on_drag
