"""`pipe schema` and `pipe describe --json` checked by an independent JSON Schema validator:
every shipped pipeline validates against the generated schema, and mistakes a user makes
(a misspelled parameter, a wrong type, an unknown stage) are rejected by it, as `pipe
validate` rejects them.

The `pipe` binary is $PIPE (the Makefile passes target/release/pipe).
"""

import json
import os
import subprocess
from pathlib import Path

import jsonschema
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
PIPE = str((ROOT / os.environ.get("PIPE", "target/release/pipe")).resolve())
PIPELINES = sorted((ROOT / "pipelines").glob("*.yaml"))


@pytest.fixture(scope="module")
def schema():
    out = subprocess.run([PIPE, "schema"], check=True, capture_output=True, text=True).stdout
    s = json.loads(out)
    jsonschema.Draft202012Validator.check_schema(s)
    return s


@pytest.mark.parametrize("path", PIPELINES, ids=[p.name for p in PIPELINES])
def test_every_shipped_pipeline_validates(schema, path):
    jsonschema.validate(yaml.safe_load(path.read_text()), schema,
                        cls=jsonschema.Draft202012Validator)


def test_schema_rejects_what_validate_rejects(schema):
    doc = yaml.safe_load((ROOT / "pipelines/spheres.yaml").read_text())
    step = next(s for s in doc["stages"] if s["use"] == "packing.rsa")
    bad_key = json.loads(json.dumps(doc))
    next(s for s in bad_key["stages"] if s["id"] == step["id"]).setdefault("with", {})["volume_fractoin"] = 0.3
    bad_type = json.loads(json.dumps(doc))
    next(s for s in bad_type["stages"] if s["id"] == step["id"]).setdefault("with", {})["periodic"] = "yes"
    bad_stage = json.loads(json.dumps(doc))
    bad_stage["stages"][0]["use"] = "packing.rsb"
    for bad in (bad_key, bad_type, bad_stage):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, schema, cls=jsonschema.Draft202012Validator)


def test_describe_json_lists_every_stage_with_words_not_rust_types():
    out = subprocess.run([PIPE, "describe", "--json"], check=True, capture_output=True,
                         text=True).stdout
    d = json.loads(out)
    listed = subprocess.run([PIPE, "list", "--markdown"], check=True, capture_output=True,
                            text=True).stdout
    ids = {s["id"] for s in d["stages"]}
    assert all(f"`{i}`" in listed for i in ids) and len(ids) >= 18
    for s in d["stages"]:
        for p in s["params"]:
            assert p["doc"] and p["type"], (s["id"], p["name"])
            for word in ("f64", "usize", "Q<", "Vec<"):
                assert word not in p["type"], (s["id"], p["name"], p["type"])
            # The schema's default is the describe default, and it validates against the
            # parameter's own schema.
            jsonschema.validate(p["default"], p["schema"])
