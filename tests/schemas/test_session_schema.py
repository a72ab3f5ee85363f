"""The JSON Schema (for rig builders) and the models accept and reject the same manifests."""

from __future__ import annotations

import copy
import json
import re

import jsonschema
import numpy as np
import pytest
from pydantic import BaseModel, ValidationError

from graspcap.schemas import session as schema_module
from graspcap.schemas.session import FORMAT, SessionManifest, json_schema
from tests.conftest import REPO
from tests.session_factory import DELETE, base_manifest, merge

DESIGN = REPO.parent / "shared" / "design" / "session-format.md"
NAN = float("nan")


def _validator() -> jsonschema.Draft202012Validator:
    schema = json_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def _model_ok(manifest: dict) -> bool:
    try:
        SessionManifest.model_validate(manifest)
    except ValidationError:
        return False
    return True


def _K(**cells) -> list[list[float]]:
    K = [[70.0, 0.0, 40.0], [0.0, 70.0, 30.0], [0.0, 0.0, 1.0]]
    for name, value in cells.items():
        K[int(name[1])][int(name[2])] = value
    return K


def _T(**cells) -> list[list[float]]:
    T = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0.5], [0, 0, 0, 1.0]]
    for name, value in cells.items():
        T[int(name[1])][int(name[2])] = value
    return T


def _view(**kw) -> dict:
    return {"scan": {"views": [{"thermal": "t.png", "depth": "d.png", "angle_deg": 0.0, **kw}]}}


# (name, overrides, valid): both validators must give `valid`.
AGREE = [
    ("valid", {}, True),
    ("dist 4", {"color_camera": {"dist": [0, 0, 0, 0]}}, True),
    ("dist 8", {"color_camera": {"dist": [0.0] * 8}}, True),
    ("dist 14", {"thermal_camera": {"dist": [0.0] * 14}}, True),
    ("integral float count", {"grasp": {"count": 4.0}}, True),
    ("left hand", {"hand": "left"}, True),
    ("no keypoints", {"grasp": {"keypoints": DELETE}}, True),
    ("null keypoints", {"grasp": {"keypoints": None}}, True),
    ("no color, keypoints", {"grasp": {"color": DELETE}}, True),
    ("no stage1 color", {"stage1": {"color": DELETE}}, True),
    ("steady_from 2", {"grasp": {"steady_from": 2}}, True),
    ("no steady_from", {"grasp": {"steady_from": DELETE}}, True),
    ("OBJ mesh", {"object_mesh": "meshes/Object.OBJ"}, True),
    ("missing key", {"turntable": DELETE}, False),
    ("missing nested key", {"grasp": {"depth": DELETE}}, False),
    ("unknown key", {"operator": "ann"}, False),
    ("unknown nested key", {"color_camera": {"fov": 60}}, False),
    ("unknown thermal key", {"thermal_camera": {"fov": 60}}, False),
    ("unknown view key", _view(mask="m.png"), False),
    ("wrong format version", {"format": "grasp-capture-session/2"}, False),
    ("bad hand", {"hand": "both"}, False),
    ("string width", {"color_camera": {"width": "80"}}, False),
    ("float width", {"color_camera": {"width": 80.5}}, False),
    ("bool width", {"color_camera": {"width": True}}, False),
    ("string fps", {"grasp": {"fps": "30"}}, False),
    ("zero fps", {"grasp": {"fps": 0}}, False),
    ("negative count", {"grasp": {"count": -3}}, False),
    ("zero count", {"grasp": {"count": 0}}, False),
    ("negative steady_from", {"grasp": {"steady_from": -1}}, False),
    ("zero depth scale", {"depth_scale_m": 0}, False),
    ("dist 6", {"color_camera": {"dist": [0.0] * 6}}, False),
    ("K 2 rows", {"color_camera": {"K": _K()[:2]}}, False),
    ("K fx <= 0", {"color_camera": {"K": _K(k00=-70.0)}}, False),
    ("K last row", {"color_camera": {"K": _K(k21=0.5)}}, False),
    ("K string cell", {"color_camera": {"K": _K(k02="40")}}, False),
    ("T 3 rows", {"turntable": {"T_color_turntable": _T()[:3]}}, False),
    ("pattern without index", {"grasp": {"depth": "grasp/depth/0.png"}}, False),
    ("pattern with other name", {"grasp": {"depth": "grasp/{frame:06d}.png"}}, False),
    ("absolute path", {"stage1": {"depth": "/data/depth.png"}}, False),
    ("dotdot path", {"stage1": {"depth": "../depth.png"}}, False),
    ("dotdot inside path", {"object_mesh": "a/../../object.ply"}, False),
    ("empty path", _view(depth=""), False),
    ("mesh not ply/obj/stl", {"object_mesh": "object.glb"}, False),
    ("neither color nor keypoints", {"grasp": {"color": DELETE, "keypoints": DELETE}}, False),
    ("null color, no keypoints", {"grasp": {"color": None, "keypoints": DELETE}}, False),
    ("no views", {"scan": {"views": []}}, False),
    ("view without angle", {"scan": {"views": [{"thermal": "t.png", "depth": "d.png"}]}}, False),
    ("empty session_id", {"session_id": ""}, False),
    ("null object_mesh", {"object_mesh": None}, False),
    ("path with a trailing newline", {"stage1": {"depth": "stage1/depth.png\n"}}, False),
    ("mesh path with a trailing newline", {"object_mesh": "object.ply\n"}, False),
    ("pattern with a tab", {"grasp": {"depth": "grasp/\t{index:06d}.png"}}, False),
    ("path with a space", {"stage1": {"depth": "stage 1/depth.png"}}, True),
    ("session_id with dots", {"session_id": "p03.mug_use-01"}, True),
    ("session_id of 128", {"session_id": "s" * 128}, True),
    ("session_id of 129", {"session_id": "s" * 129}, False),
    ("session_id of 300", {"session_id": "s" * 300}, False),
    ("session_id with newline", {"session_id": "p01\n"}, False),
    ("session_id with NUL", {"session_id": "p01\0x"}, False),
    ("session_id climbing out", {"session_id": "../../../../tmp/escaped-session"}, False),
    ("session_id with slash", {"session_id": "a/b"}, False),
    ("session_id starting with dot", {"session_id": ".hidden"}, False),
    ("session_id with space", {"session_id": "p01 mug"}, False),
    ("Infinity in dist", {"color_camera": {"dist": [float("inf"), 0, 0, 0]}}, False),
    ("dist 1e300", {"thermal_camera": {"dist": [1e300, 0, 0, 0]}}, False),
    ("real Kinect dist", {"color_camera": {"dist": [0.1, -0.25, 0.001, -0.002, 0.08]}}, True),
    ("count 10^12", {"grasp": {"count": 10**12}}, False),
    ("count at the limit", {"grasp": {"count": 100_000}}, True),
    ("depth scale 5 m", {"depth_scale_m": 5.0}, False),
    ("721 views", {"scan": {"views": [{"thermal": "t.png", "depth": "d.png",
                                        "angle_deg": 0.5 * j} for j in range(721)]}}, False),
]

# Checks JSON Schema cannot express: the JSON Schema accepts these, the models reject them.
MODEL_ONLY = [
    ("principal point outside image", {"color_camera": {"K": _K(k02=120.0)}}),
    ("large skew", {"color_camera": {"K": _K(k01=5.0)}}),
    ("non-rigid T (scaled)", {"turntable": {"T_color_turntable": _T(k00=2.0)}}),
    ("reflection T", {"turntable": {"T_color_turntable": _T(k22=-1.0)}}),
    ("T last row", {"thermal_camera": {"T_color_thermal": _T(k30=0.2)}}),
    ("NaN in K (fx)", {"color_camera": {"K": _K(k00=NAN)}}),
    ("Infinity in K (cx)", {"color_camera": {"K": _K(k02=float("inf"))}}),
    ("NaN in T", {"thermal_camera": {"T_color_thermal": _T(k03=NAN)}}),
    ("NaN angle", _view(angle_deg=NAN)),
    ("steady_from >= count", {"grasp": {"steady_from": 4}}),
    ("bad format spec", {"grasp": {"depth": "grasp/{index:06q}.png"}}),
    ("extra format field", {"grasp": {"depth": "grasp/{index}/{camera}.png"}}),
    ("pattern ignores index", {"grasp": {"depth": "grasp/{index!s:.0}.png"}}),
    ("pattern attribute", {"grasp": {"depth": "grasp/{index.nope}.png"}}),
    ("pattern item", {"grasp": {"depth": "grasp/{index[0]}.png"}}),
    ("pattern unbalanced brace", {"grasp": {"depth": "grasp/{index:06d}}.png"}}),
    ("pattern nested spec", {"grasp": {"depth": "grasp/{index:{index}}.png"}}),
    ("pattern of a gigabyte", {"grasp": {"keypoints": "k/{index:0999999999d}.json"}}),
    ("fx 1e300", {"color_camera": {"K": _K(k00=1e300)}}),
    ("thermal focal 100x", {"thermal_camera": {"K": [[3500.0, 0, 20.0], [0, 3500.0, 16.0],
                                                     [0, 0, 1]]}}),
    ("fov over 170 degrees", {"color_camera": {"K": _K(k00=3.0, k11=3.0)}}),
    ("fy 10x fx", {"color_camera": {"K": _K(k11=700.0)}}),
    ("camera of 60000 x 60000", {"color_camera": {"width": 60000, "height": 60000,
                                                  "K": _K(k00=40000.0, k11=40000.0)}}),
]


@pytest.fixture(scope="module")
def validator() -> jsonschema.Draft202012Validator:
    return _validator()


def test_enough_cases():
    assert len(AGREE) + len(MODEL_ONLY) >= 20
    assert sum(not valid for _, _, valid in AGREE) >= 20


@pytest.mark.parametrize(("name", "overrides", "valid"), AGREE, ids=[c[0] for c in AGREE])
def test_schema_and_models_agree(validator, name, overrides, valid):
    manifest = merge(base_manifest(), overrides)
    schema_errors = list(validator.iter_errors(manifest))
    assert (not schema_errors) == valid, [e.message for e in schema_errors]
    assert _model_ok(manifest) == valid


@pytest.mark.parametrize(("name", "overrides"), MODEL_ONLY, ids=[c[0] for c in MODEL_ONLY])
def test_model_only_checks(validator, name, overrides):
    manifest = merge(base_manifest(), overrides)
    assert list(validator.iter_errors(manifest)) == []
    assert not _model_ok(manifest)


def _fields(model: type[BaseModel]) -> dict[str, bool]:
    return {name: info.is_required() for name, info in model.model_fields.items()}


def _resolve(schema: dict, node: dict) -> dict:
    """Merge a property node with the $ref/allOf parts it is built from."""
    out = dict(node)
    for part in node.get("allOf", []) + ([node] if "$ref" in node else []):
        if "$ref" in part:
            ref = schema["$defs"][part["$ref"].split("/")[-1]]
            out = {**ref, **{k: v for k, v in out.items() if k != "$ref"},
                   "properties": {**ref.get("properties", {}), **out.get("properties", {})},
                   "required": ref.get("required", []) + out.get("required", [])}
    return out


@pytest.mark.parametrize(
    ("path", "model"),
    [((), SessionManifest), (("color_camera",), schema_module.ColorCamera),
     (("thermal_camera",), schema_module.ThermalCamera), (("turntable",), schema_module.Turntable),
     (("stage1",), schema_module.Stage1), (("grasp",), schema_module.Grasp)],
)
def test_schema_fields_match_model_fields(path, model):
    """Same keys, same required set, and a description for every key a rig builder reads."""
    schema = json_schema()
    node = schema
    for key in path:
        node = _resolve(schema, node["properties"][key])
    props = node["properties"]
    assert set(props) == set(model.model_fields)
    required = {name for name, req in _fields(model).items() if req}
    assert set(node["required"]) == required
    for name, prop in props.items():
        assert prop.get("description", "").strip(), f"{path}.{name} has no description"
        assert model.model_fields[name].description, f"model field {name} has no docstring"


def test_view_fields_match():
    view = json_schema()["$defs"]["scan_view"]
    assert set(view["properties"]) == set(schema_module.ScanView.model_fields)
    assert set(view["required"]) == {"thermal", "depth", "angle_deg"}


def test_format_constant():
    assert json_schema()["properties"]["format"]["const"] == FORMAT == "grasp-capture-session/1"


def _design_example() -> dict:
    """The session.json example of session-format.md with its ``[[...]]`` filled in."""
    text = DESIGN.read_text()
    block = re.search(r"## session.json\s+```json\n(.*?)```", text, re.S).group(1)
    thermal_K = "[[400.0, 0, 160.0], [0, 400.0, 128.0], [0, 0, 1]]"
    block = block.replace('"K": [[...]]', f'"K": {thermal_K}')
    T = json.dumps(_T(k03=0.05))
    block = block.replace("[[...4x4...]]", T)
    return json.loads(block)


def test_design_example_validates(validator):
    if not DESIGN.is_file():
        pytest.skip("session-format.md is not beside the repository")
    example = _design_example()
    assert list(validator.iter_errors(example)) == []
    manifest = SessionManifest.model_validate(example)
    assert manifest.grasp.frame_path("depth", 299) == "grasp/depth/000299.png"
    assert manifest.grasp.steady_from is None
    assert manifest.color_camera.K_array()[0, 0] == pytest.approx(615.0)
    assert manifest.thermal_camera.T_color_thermal_array().shape == (4, 4)


def test_models_are_frozen_and_arrays_are_copies():
    manifest = SessionManifest.model_validate(base_manifest())
    with pytest.raises(ValidationError):
        manifest.hand = "left"
    K = manifest.color_camera.K_array()
    K[0, 0] = -1
    assert manifest.color_camera.K[0][0] == 70.0
    turntable = copy.deepcopy(base_manifest()["turntable"]["T_color_turntable"])
    np.testing.assert_allclose(manifest.turntable.T_color_turntable_array(), turntable, atol=1e-12)
