"""The scene file's declared schema (`lierk.app.scene_schema`): ``lierk
schema`` prints it as JSON Schema, every example validates against it, and
msgspec's errors become one line naming the key's path.

No JAX program is compiled here.  ``jsonschema`` is not a dependency, so
`_validate` checks a document against the subset of JSON Schema that msgspec
writes, and refuses any keyword outside it (the test then says which)."""

from __future__ import annotations

import json
import pathlib
import re
import subprocess
import sys
import tomllib

import pytest
from helpers import run_inprocess

from lierk.app import scene_schema
from lierk.app.scene import from_dict

EXAMPLES = sorted((pathlib.Path(__file__).resolve().parent.parent / "examples").glob("*.toml"))
KNOWN = {
    "$schema",
    "$defs",
    "$ref",
    "anyOf",
    "discriminator",
    "type",
    "enum",
    "properties",
    "required",
    "additionalProperties",
    "items",
    "minItems",
    "maxItems",
    "minimum",
    "maximum",
    "exclusiveMinimum",
    "pattern",
    "title",
    "description",
    "default",
    "examples",
}
TYPES = {"object": dict, "array": list, "string": str, "boolean": bool, "integer": int, "number": (int, float)}


def _validate(x, s: dict, root: dict, path: str = "$") -> list[str]:
    """The reasons ``x`` does not match ``s`` (empty if it does)."""
    assert set(s) <= KNOWN, f"{path}: keywords the test does not check: {set(s) - KNOWN}"
    if "$ref" in s:
        return _validate(x, root["$defs"][s["$ref"].removeprefix("#/$defs/")], root, path)
    if "anyOf" in s:
        if "discriminator" in s and isinstance(x, dict):
            ref = s["discriminator"]["mapping"].get(x.get(s["discriminator"]["propertyName"]))
            return _validate(x, {"$ref": ref}, root, path) if ref else [f"{path}: no such kind"]
        return [] if any(not _validate(x, u, root, path) for u in s["anyOf"]) else [f"{path}: matches no anyOf"]
    t = s.get("type")
    if t and (not isinstance(x, TYPES[t]) or (isinstance(x, bool) and t != "boolean")):
        return [f"{path}: not {t}"]
    errors = []
    if "enum" in s and x not in s["enum"]:
        errors.append(f"{path}: not in {s['enum']}")
    for key, ok in (
        ("minimum", lambda b: x >= b),
        ("maximum", lambda b: x <= b),
        ("exclusiveMinimum", lambda b: x > b),
        ("minItems", lambda b: len(x) >= b),
        ("maxItems", lambda b: len(x) <= b),
        ("pattern", lambda b: re.search(b, x)),
    ):
        if key in s and not ok(s[key]):
            errors.append(f"{path}: {key} {s[key]}")
    if isinstance(x, dict):
        errors += [f"{path}: missing {k}" for k in s.get("required", ()) if k not in x]
        for k, v in x.items():
            if k in s.get("properties", {}):
                errors += _validate(v, s["properties"][k], root, f"{path}.{k}")
            elif s.get("additionalProperties") is False:
                errors.append(f"{path}: unknown {k}")
    if isinstance(x, list) and "items" in s:
        for i, v in enumerate(x):
            errors += _validate(v, s["items"], root, f"{path}[{i}]")
    return errors


@pytest.fixture(scope="module")
def printed() -> dict:
    """The JSON Schema as ``lierk schema`` prints it."""
    out = subprocess.run([sys.executable, "-m", "lierk.app.cli", "schema"], capture_output=True, text=True, check=True)
    schema = json.loads(out.stdout)
    assert schema == scene_schema.json_schema()
    return schema


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_every_example_validates_against_the_printed_schema(path, printed):
    d = tomllib.loads(path.read_text())
    assert _validate(d, printed, printed) == []
    scene_schema.parse(d)


def test_the_schema_declares_every_kind_and_table(printed):
    defs, top = printed["$defs"], printed["$defs"]["SceneFile"]
    assert printed["$ref"] == "#/$defs/SceneFile" and top["required"] == ["body", "initial", "run"]
    kinds = {
        name: set(s["discriminator"]["mapping"])
        for name, s in [
            ("body", top["properties"]["body"]),
            ("effects", top["properties"]["effects"]["items"]),
            ("events", top["properties"]["events"]["items"]),
            ("parts", defs["CompositeBody"]["properties"]["parts"]["items"]),
        ]
    }
    assert kinds == {
        "body": {"tee_handle", "box", "cylinder", "sphere", "composite", "tensor", "mesh"},
        "effects": {
            "gravity",
            "body_torque",
            "space_torque",
            "timed_torque",
            "damping",
            "gravity_gradient",
            "magnetic",
            "rotor",
            "reaction_wheels",
        },
        "events": {"flip", "tilt", "tilt_extremum", "pointing", "energy", "momentum"},
        "parts": {"box", "cylinder", "sphere"},
    }
    assert defs["Run"]["required"] == ["solver", "t1"] and defs["Initial"]["required"] == ["omega"]
    assert defs["Run"]["properties"]["dt"] == {
        "type": "number",
        "exclusiveMinimum": 0,
        "description": "the fixed step (s).",
    }
    for name, table in defs.items():
        assert table["additionalProperties"] is False and table["description"], name
        # Each key is described once, in its table's docstring (which the docs
        # page shows), and the description gives the default the key has.
        described = scene_schema._keys(scene_schema._TABLES[name])
        assert set(described) == set(table["properties"]) - {"kind"}, name
        for key, prop in table["properties"].items():
            assert key == "kind" or prop["description"] == described[key], (name, key)
            if prop.get("default") not in (None, "", []):
                said = re.search(r"default (\[.*?\]|\S+?)[.,;]?(?:\s|$)", described[key])
                assert said and json.loads(said[1]) == prop["default"], (name, key, described[key])
    # The solver's name: any letter case, as loading takes it; the canonical names complete.
    solver = defs["Run"]["properties"]["solver"]
    assert (
        "RKMK4" in solver["examples"]
        and re.search(solver["pattern"], "dp54")
        and not re.search(solver["pattern"], "RK45")
    )


BAD = [
    (
        {"colour": "red"},
        "scene: unknown key 'colour' (= 'red'); allowed keys: body, description, effects, events, initial, name, run",
    ),
    ({"run": {"solver": "RKMK4", "dt": -1, "t1": 1.0}}, "run.dt must be > 0, got -1"),
    ({"run": {"solver": "RKMK4", "dt": 0.1}}, "run: missing required key 't1'"),
    (
        {"body": {"kind": "cube"}},
        "body.kind = 'cube' is not allowed; choose one of: 'tee_handle', 'box', 'cylinder', "
        "'sphere', 'composite', 'tensor', 'mesh'",
    ),
    (
        {"effects": [{"kind": "damping", "c": 0.1}, {"kind": "gravity", "pivot_to_com": [0, 0, "x"]}]},
        "effects[1].pivot_to_com[2] must be a finite number, got 'x'",
    ),
    (
        {"effects": [{"kind": "gravity", "pivot_to_com": [0, 0, 1], "g": False}]},
        "effects[0].g must be a finite number, got False",
    ),
    ({"events": [{"kind": "tilt", "angle": 4}]}, "events[0].angle must be in [0, pi] rad, got 4"),
    ({"initial": {"omega": [1, 0]}}, "initial.omega must be a list of 3 numbers, got [1, 0]"),
    (
        {"body": {"kind": "cylinder", "mass": 1, "radius": 1, "length": 1, "axis": "w"}},
        "body.axis = 'w' is not allowed; choose one of: 'x', 'y', 'z'",
    ),
]


@pytest.mark.parametrize("change, message", BAD, ids=[m.split(" ")[0] for _, m in BAD])
def test_the_json_schema_and_loading_refuse_the_same_mistakes(printed, change, message):
    d = {
        "body": {"kind": "tee_handle"},
        "initial": {"omega": [1.0, 0.05, 0.0]},
        "run": {"solver": "RKMK4", "dt": 0.01, "t1": 1.0},
        **change,
    }
    assert _validate(d, printed, printed) != []
    with pytest.raises(ValueError) as e:
        scene_schema.parse(d)
    assert str(e.value) == message


def test_numbers_must_be_finite_and_the_rules_across_keys_are_left_to_loading(printed):
    # TOML has inf and nan; JSON, and so JSON Schema, has neither.
    d = tomllib.loads(
        '[body]\nkind = "tensor"\ninertia = [[1, 0, 0], [0, 2, 0], [0, 0, inf]]\n'
        '[initial]\nomega = [1, 0, 0]\n[run]\nsolver = "DP54"\nrtol = 1e-8\nt1 = 1'
    )
    with pytest.raises(ValueError, match=r"^body.inertia\[2\]\[2\] must be a finite number, got inf$"):
        scene_schema.parse(d)
    both = {
        "body": {"kind": "tee_handle"},
        "initial": {"omega": [1.0, 0.0, 0.0]},
        "run": {"solver": "RKMK4", "dt": 0.01, "rtol": 1e-6, "t1": 1.0},
    }
    assert _validate(both, printed, printed) == [] and scene_schema.parse(both).run.rtol == 1e-6
    with pytest.raises(ValueError, match="give exactly one of 'dt'"):
        from_dict(both)


def test_lierk_schema_on_the_command_line(capsys):
    code, out, err = run_inprocess(["schema"], capsys)
    assert code == 0 and err == "" and json.loads(out) == scene_schema.json_schema()
    code, out, err = run_inprocess(["schema", "--help"], capsys)
    assert code == 0 and out.startswith("usage: lierk schema") and "JSON Schema" in out


def test_import_lierk_does_not_import_msgspec():
    code = "import sys, lierk; print('msgspec' in sys.modules)"
    assert (
        subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
        == "False"
    )
