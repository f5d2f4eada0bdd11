"""Where the viewer listens: viser imported on demand (an optional dependency) and the
port checks that make ``--port N`` refuse a taken port in one line (viser alone would move
to the next free one)."""

from __future__ import annotations

import socket
from typing import Any

from fem3d.errors import InputError

__all__ = ["check_port_free", "free_port", "import_viser"]


def import_viser() -> Any:
    """viser, imported when a viewer starts: it is an optional dependency (fem3d[view])."""
    try:
        import viser
    except ImportError as exc:
        raise InputError(
            "the viewer needs viser: pip install 'fem3d[view]' (viser==1.1.1)"
        ) from exc
    return viser


def free_port(host: str) -> int:
    """A port nobody listens on now (``--port 0``)."""
    with socket.socket(_family(host), socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def _family(host: str) -> socket.AddressFamily:
    return socket.AF_INET6 if ":" in host else socket.AF_INET


def check_port_free(host: str, port: int) -> None:
    """Raise InputError (one line) when ``host:port`` cannot be listened on."""
    with socket.socket(_family(host), socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            why = "is in use" if exc.errno in (98, 48) else f"cannot be used ({exc.strerror})"
            raise InputError(
                f"port {port} on {host} {why}; pick another with --port N, "
                "or --port 0 for a free one"
            ) from None
