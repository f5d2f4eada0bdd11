"""Key paths into a scene: ``"bodies[0].material.E"`` <-> ``["bodies", 0, "material", "E"]``.

Error messages name a setting by its key path (:func:`format_key`), and
:func:`fem3d.scene.load.apply_overrides` and :meth:`fem3d.scene.spec.Scene.to_dict` set a value
in a scene's dict by one (:func:`parse_key`, :func:`set_path`). Both sides of the scene
package use them, so they live apart from either (no import circle).
"""

from __future__ import annotations

import re
from typing import Any

from fem3d.errors import InputError

__all__ = ["format_key", "parse_key", "set_path"]


def format_key(loc: tuple) -> str:
    """``("bodies", 0, "mesh")`` -> ``"bodies[0].mesh"`` (``"(top level)"`` when empty)."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            text = str(part)
            if not text.isidentifier():  # a key with odd characters (a newline...) stays on
                text = repr(text)        # one line of the message, visibly
            out += ("." if out else "") + text
    return out or "(top level)"


_PART = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)|\[(-?\d+)\]")


def parse_key(key: str, source: str = "override") -> list[str | int]:
    """``"bodies[0].material.E"`` -> ``["bodies", 0, "material", "E"]``."""
    parts: list[str | int] = []
    pos = 0
    key = key.strip()
    while pos < len(key):
        if key[pos] == "." and parts and pos + 1 < len(key):
            pos += 1
        m = _PART.match(key, pos)
        if m is None:
            raise InputError(f"{key}: not a key path (like bodies[0].material.E)", path=source)
        parts.append(m.group(1) if m.group(1) is not None else int(m.group(2)))
        pos = m.end()
    if not parts or not isinstance(parts[0], str):
        raise InputError(f"{key}: not a key path (like bodies[0].material.E)", path=source)
    return parts


def set_path(d: Any, parts: list[str | int], value: Any, key: str = "",
            source: str = "override") -> None:
    """Set ``value`` at key path ``parts`` in the nested dicts and lists ``d``, creating
    missing tables and lists on the way.

    Raises
    ------
    InputError
        ``SOURCE: key: ...`` for an index out of range or a step into a value that is not a
        table or a list (``key``: how the caller wrote the path; default its parts).
    """
    node = d
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        here = format_key(tuple(parts[: i + 1]))
        if isinstance(part, int):
            if not isinstance(node, list):
                raise InputError(f"{key or here}: {format_key(tuple(parts[:i]))} is not a list",
                                 path=source)
            if not -len(node) <= part < len(node):
                raise InputError(f"{key or here}: index {part} out of range (there are "
                                 f"{len(node)})", path=source)
        else:
            if not isinstance(node, dict):
                raise InputError(f"{key or here}: {format_key(tuple(parts[:i])) or 'scene'} is "
                                 f"not a table", path=source)
        if last:
            node[part] = value
            return
        nxt = node[part] if isinstance(part, int) else node.get(part)
        if nxt is None:
            nxt = [] if isinstance(parts[i + 1], int) else {}
            node[part] = nxt
        node = nxt
