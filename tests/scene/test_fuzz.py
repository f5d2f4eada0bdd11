"""Fuzzing the scene loader: mutated and random TOML raise InputError and nothing else."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fem3d.errors import InputError
from fem3d.scene import Scene, load_scene, read_scene_file

ROOT = Path(__file__).resolve().parents[2]
SCENES = ROOT / "data" / "scenes"
TEXTS = {p.stem: p.read_text() for p in sorted(SCENES.glob("*.toml"))}
# the shipped scenes with their relative paths made absolute (so mutants can load meshes)
for name, text in TEXTS.items():
    TEXTS[name] = (text.replace('"../', f'"{ROOT / "data"}/')
                   .replace('"meshes/', f'"{SCENES / "meshes"}/'))


def toml_value(v) -> str:
    """A TOML inline value (enough for the fuzzer's dicts, lists and scalars)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else
                                             "-inf" if v == -math.inf else repr(v))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(str(k))} = {toml_value(x)}" for k, x in v.items()) + "}"


def toml_dumps(d: dict) -> str:
    return "".join(f"{json.dumps(str(k))} = {toml_value(v)}\n" for k, v in d.items())


def load_text(tmp: Path, text: str) -> None:
    p = tmp / "fuzz.toml"
    # a new inode per example: truncating the old file makes ext4 flush it on close (ms each)
    p.unlink(missing_ok=True)
    p.write_text(text, encoding="utf-8", errors="surrogatepass")
    try:
        read_scene_file(p)
    except InputError as exc:
        assert "\n" not in str(exc) and str(exc).startswith(str(p))


scalars = st.one_of(st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True),
                    st.text(max_size=8))
values = st.recursive(scalars, lambda c: st.one_of(
    st.lists(c, max_size=4), st.dictionaries(st.text(max_size=6), c, max_size=4)), max_leaves=12)
KEYS = ["simulation", "bodies", "pulls", "output", "interaction", "contact", "obstacles",
        "name", "dt", "mesh", "material", "E", "nu", "select", "box", "pins", "motion",
        "keyframes", "t", "offset", "steps", "gravity", "velocity", "transform"]


def mutate(d, data) -> None:
    """One random change somewhere in the nested dict/list ``d``."""
    node = d
    for _ in range(data.draw(st.integers(0, 4))):
        children = list(node.items()) if isinstance(node, dict) else list(enumerate(node))
        children = [(k, v) for k, v in children if isinstance(v, dict | list) and v]
        if not children:
            break
        node = data.draw(st.sampled_from(children))[1]
    action = data.draw(st.sampled_from(["set", "delete", "add"]))
    if isinstance(node, dict):
        key = (data.draw(st.sampled_from(sorted(node))) if node and action != "add"
               else data.draw(st.one_of(st.sampled_from(KEYS), st.text(max_size=6))))
        if action == "delete":
            node.pop(key, None)
        else:
            node[key] = data.draw(values)
    elif node:
        i = data.draw(st.integers(0, len(node) - 1))
        if action == "delete":
            node.pop(i)
        else:
            node[i] = data.draw(values)


@settings(max_examples=120, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(st.data())
def test_mutated_scene_dicts_raise_only_input_error(tmp_path, data):
    name = data.draw(st.sampled_from(sorted(TEXTS)))
    d = tomllib.loads(TEXTS[name])
    for _ in range(data.draw(st.integers(1, 3))):
        mutate(d, data)
    load_text(tmp_path, toml_dumps(d))
    try:
        Scene.from_dict(d)
    except InputError as exc:
        assert "\n" not in str(exc)


@settings(max_examples=120, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_mutated_scene_text_raises_only_input_error(tmp_path, data):
    text = TEXTS[data.draw(st.sampled_from(sorted(TEXTS)))]
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(text)))
        kind = data.draw(st.sampled_from(["insert", "delete", "replace"]))
        piece = data.draw(st.sampled_from(["=", "[", "]", "{", "}", '"', ",", "\n", "#", ".",
                                           "0", "-1", "1e400", "x", "nan", "true", " "]))
        if kind == "insert":
            text = text[:i] + piece + text[i:]
        elif kind == "delete":
            text = text[:i] + text[i + data.draw(st.integers(1, 5)):]
        else:
            text = text[:i] + piece + text[i + 1:]
    load_text(tmp_path, text)


@settings(max_examples=100, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.one_of(st.text(max_size=200), st.binary(max_size=200).map(
    lambda b: b.decode("latin-1"))))
def test_random_text_raises_only_input_error(tmp_path, text):
    load_text(tmp_path, text)


def test_a_key_with_a_newline_is_named_on_one_line():
    """Found by the mutated-dict test above: an unknown key "\\n" printed raw split the one-line
    error in two; odd keys are quoted."""
    d = load_scene("arma").to_dict()
    d["\n"] = 1
    with pytest.raises(InputError) as info:
        Scene.from_dict(d)
    assert "\n" not in str(info.value)
    assert "'\\n': unknown key" in str(info.value)
