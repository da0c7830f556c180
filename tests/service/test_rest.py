"""REST API with the FastAPI TestClient: results, unit handling and the bad-input catalogue."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from service.api.protocol import encode_binary
from service.app import create_app
from service.core.segments import SEGMENTS
from service.settings import Settings
from tests.service.conftest import write_tiny_model


def _window(n: int = 128, rate: float = 60.0, **extra) -> dict:
    t = np.arange(n) / rate
    rows = np.stack([np.sin(t), np.cos(t), 9.81 + 0 * t, 2 * np.sin(3 * t), 0 * t, np.cos(2 * t)], axis=1)
    return {"samples": rows.tolist(), "sample_rate_hz": rate, **extra}


def test_health_ready_models_metrics(client: TestClient) -> None:
    assert client.get("/health").json() == {"status": "alive"}
    assert client.get("/ready").json()["ready"] is True
    models = client.get("/v1/models").json()
    assert set(models) == {"i2s_assignment", "i2s_alignment"}
    client.post("/v1/imu/windows", json={"windows": [_window()]})
    text = client.get("/metrics").text
    assert "wearmocap_requests_total" in text and "wearmocap_inference_batch_windows_count" in text


def test_window_result_shape(client: TestClient) -> None:
    r = client.post("/v1/imu/windows", json={"windows": [_window(), _window(segment="Pelvis")]})
    assert r.status_code == 200, r.text
    res = r.json()["results"]
    assert len(res) == 2
    assert abs(sum(res[0]["probabilities"].values()) - 1) < 1e-5
    q = np.array(res[1]["alignment"]["q_segment_imu"])
    assert res[1]["alignment"]["segment"] == "Pelvis"
    assert abs(np.linalg.norm(q) - 1) < 1e-5 and q[0] >= 0
    R = np.array(res[1]["alignment"]["R_segment_imu"])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)


def test_units_are_converted(client: TestClient) -> None:
    w = _window()
    x = np.array(w["samples"])
    scaled = np.concatenate([x[:, :3] / 9.80665, np.degrees(x[:, 3:])], axis=1)
    a = client.post("/v1/imu/windows", json={"windows": [w]}).json()["results"][0]["probabilities"]
    b = client.post(
        "/v1/imu/windows", json={"windows": [{"samples": scaled.tolist(), "acc_unit": "g", "gyr_unit": "deg/s"}]}
    ).json()["results"][0]
    np.testing.assert_allclose(list(a.values()), list(b["probabilities"].values()), atol=1e-5)


def test_other_rates_are_resampled(client: TestClient) -> None:
    assert client.post("/v1/imu/windows", json={"windows": [_window(214, 100.0)]}).status_code == 200
    r = client.post("/v1/imu/windows", json={"windows": [_window(200, 100.0)]})
    assert r.status_code == 422 and "at least 214 samples" in r.json()["detail"]


@pytest.mark.parametrize(
    "window, fragment",
    [
        (_window(127), "128 samples, got 127"),
        ({"samples": [[0.0] * 5] * 128}, "samples.0: List should have at least 6 items"),
        (_window(rate=5.0), "sample_rate_hz: Input should be greater than or equal to 10"),
        (_window(acc_unit="ft/s^2"), "acc_unit"),
        (_window(gyr_unit="rpm"), "gyr_unit"),
        (_window(segment="Head"), "segment"),
        (
            {"samples": [[2e6, 0.0, 9.81, 0.0, 0.0, 0.0]] * 128},
            "samples.0.0: Input should be less than or equal to 1000000",
        ),
    ],
)
def test_bad_windows_are_422_with_a_message(client: TestClient, window: dict, fragment: str) -> None:
    r = client.post("/v1/imu/windows", json={"windows": [window]})
    assert r.status_code == 422
    assert fragment in r.text


def test_nan_and_inf_are_rejected(client: TestClient) -> None:
    for bad in ("NaN", "Infinity"):
        body = '{"windows": [{"samples": [' + ",".join([f"[{bad}, 0, 9.8, 0, 0, 0]"] * 128) + "]}]}"
        r = client.post("/v1/imu/windows", content=body, headers={"content-type": "application/json"})
        assert r.status_code == 422 and "finite" in r.text


def test_malformed_json_and_oversized_bodies(client: TestClient) -> None:
    r = client.post("/v1/imu/windows", content="{not json", headers={"content-type": "application/json"})
    assert r.status_code == 422 and "Expecting property name" in r.json()["detail"]  # the parser's reason
    big = {"windows": [_window()] * 200}
    assert client.post("/v1/imu/windows", json=big).status_code == 413


def test_the_document_states_what_the_service_refuses(client: TestClient) -> None:
    """Rates, row widths, unique segments and strict booleans are in the OpenAPI document, and enforced."""
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    window = schemas["ImuWindow"]["properties"]
    assert (window["sample_rate_hz"]["minimum"], window["sample_rate_hz"]["maximum"]) == (10, 2000)
    assert window["samples"]["items"]["minItems"] == window["samples"]["items"]["maxItems"] == 6
    assert schemas["AssignRequest"]["properties"]["worn_segments"]["anyOf"][0]["uniqueItems"] is True
    assert schemas["AssignRequest"]["properties"]["allow_shared"]["type"] == "boolean"
    sensors = [{"sensor_id": "a", "windows": [_window()]}]
    r = client.post("/v1/imu/assign", json={"sensors": sensors, "allow_shared": 0})
    assert r.status_code == 422 and "allow_shared: Input should be a valid boolean" in r.text, r.text
    r = client.post("/v1/imu/windows", json={"windows": [_window() | {"sample_rate_hz": "60"}]})
    assert r.status_code == 422 and "sample_rate_hz: Input should be a valid number" in r.text, r.text


def test_joint_assignment_endpoint(client: TestClient) -> None:
    sensors = [{"sensor_id": f"s{k}", "windows": [_window()]} for k in range(3)]
    r = client.post("/v1/imu/assign", json={"sensors": sensors})
    assert r.status_code == 200, r.text
    segs = [s["segment"] for s in r.json()["sensors"]]
    assert len(set(segs)) == 3  # one-to-one
    shared = client.post("/v1/imu/assign", json={"sensors": sensors, "allow_shared": True}).json()
    assert len({s["segment"] for s in shared["sensors"]}) == 1  # identical data, shared allowed
    dup = client.post("/v1/imu/assign", json={"sensors": sensors[:1] * 2})
    assert dup.status_code == 422 and "unique" in dup.text
    nine = [{"sensor_id": f"s{k}", "windows": [_window()]} for k in range(9)]
    out = client.post("/v1/imu/assign", json={"sensors": nine}).json()["sensors"]
    assert sum(s["segment"] is None for s in out) == 2  # more sensors than segments
    assert sum(s["window_segments"] == [None] for s in out) == 2  # and at the one moment


def test_declared_worn_segments_narrow_the_answers(client: TestClient) -> None:
    """With ``worn_segments`` the joint answer and every per-moment answer are among the declared segments; each
    window's own answer (/v1/imu/windows) is untouched. Bad declarations are 422s that say what was wrong."""
    sensors = [{"sensor_id": f"s{k}", "windows": [_window(), _window()]} for k in range(3)]
    free = client.post("/v1/imu/assign", json={"sensors": sensors}).json()["sensors"]
    worn = [name for name in SEGMENTS if name not in {s["segment"] for s in free}][:2]
    out = client.post("/v1/imu/assign", json={"sensors": sensors, "worn_segments": worn})
    assert out.status_code == 200, out.text
    got = out.json()["sensors"]
    assert sorted(s["segment"] for s in got if s["segment"]) == sorted(worn)
    assert sum(s["segment"] is None for s in got) == 1  # three sensors, two declared segments
    assert {g for s in got for g in s["window_segments"]} <= set(worn) | {None}
    assert all(s["alignment"]["segment"] == s["segment"] for s in got if s["segment"])
    for bad, fragment in (
        (["LeftFoot", "LeftFoot"], "name each segment once"),
        (["Head"], "Input should be 'LeftFoot'"),
        ([], "at least 1 item"),
    ):
        r = client.post("/v1/imu/assign", json={"sensors": sensors, "worn_segments": bad})
        assert r.status_code == 422 and fragment in r.text and "worn_segments" in r.text, r.text


def test_per_sensor_candidate_segments_narrow_that_sensors_answers(client: TestClient) -> None:
    """``candidate_segments``: one sensor declared the pelvis, two "a foot" each (side unknown), with the same data.
    The pelvis sensor gets the pelvis with a null margin (nothing else to lead), the two others one foot each, in
    the joint answer and at every moment; a declaration that contradicts ``worn_segments`` is a 422."""
    feet = ["LeftFoot", "RightFoot"]
    sensors = [{"sensor_id": f"s{k}", "windows": [_window(), _window()]} for k in range(3)]
    sensors[0]["candidate_segments"] = ["Pelvis"]
    sensors[1]["candidate_segments"] = sensors[2]["candidate_segments"] = feet
    out = client.post("/v1/imu/assign", json={"sensors": sensors})
    assert out.status_code == 200, out.text
    got = out.json()["sensors"]
    assert got[0]["segment"] == "Pelvis" and got[0]["margin"] is None and got[0]["confidence"] == 1.0
    assert sorted(s["segment"] for s in got[1:]) == feet and all(s["margin"] is not None for s in got[1:])
    assert got[0]["window_segments"] == ["Pelvis", "Pelvis"]
    assert [sorted(pair) for pair in zip(got[1]["window_segments"], got[2]["window_segments"], strict=True)] == [
        feet,
        feet,
    ]
    clash = client.post("/v1/imu/assign", json={"sensors": sensors, "worn_segments": feet})
    assert clash.status_code == 422, clash.text
    assert "sensors[0].candidate_segments: none of ['Pelvis'] is among worn_segments" in clash.text
    sensors[1]["candidate_segments"] = ["LeftFoot", "LeftFoot"]
    repeated = client.post("/v1/imu/assign", json={"sensors": sensors})
    assert repeated.status_code == 422 and "name each segment once" in repeated.text, repeated.text


def test_assign_answers_each_moment_one_to_one(client: TestClient) -> None:
    """Window k of every sensor is one moment: its windows share out the segments, whatever the sensors' totals say;
    a still window gets null, and a sensor's extra windows are assigned among the sensors that have them."""
    moving = _window()
    still = {"samples": (np.array(moving["samples"]) * [1, 1, 1, 0.01, 0.01, 0.01]).tolist()}
    sensors = [
        {"sensor_id": "a", "windows": [moving, moving, moving]},
        {"sensor_id": "b", "windows": [moving, still]},
        {"sensor_id": "c", "windows": [moving]},
    ]
    out = client.post("/v1/imu/assign", json={"sensors": sensors}).json()["sensors"]
    per_window = [s["window_segments"] for s in out]
    assert [len(w) for w in per_window] == [3, 2, 1]
    assert len({per_window[0][0], per_window[1][0], per_window[2][0]}) == 3  # one-to-one at moment 0
    assert per_window[1][1] is None  # still
    alone = client.post("/v1/imu/windows", json={"windows": [moving]}).json()["results"][0]["segment"]
    assert per_window[0][1] == per_window[0][2] == alone  # a window with no rival keeps its own answer
    shared = client.post("/v1/imu/assign", json={"sensors": sensors, "allow_shared": True}).json()["sensors"]
    assert [s["window_segments"] for s in shared] == [[alone] * 3, [alone, None], [alone]]


def test_windows_that_turn_about_the_vertical_are_flagged(client: TestClient) -> None:
    """The flag follows the window's dominant rotation axis relative to gravity, in any sensor orientation, and is
    false for still windows; /v1/imu/assign counts the flagged moving windows per sensor."""
    swing = np.array(_window()["samples"])  # rotates mostly about x, gravity along z
    twist = swing[:, [0, 1, 2, 5, 4, 3]]  # the same rates with x and z swapped: mostly about gravity
    tilted = twist @ np.kron(
        np.eye(2), np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    )  # sensor on its side
    still = swing.copy()
    still[:, 3:] *= 0.01
    windows = [{"samples": w.tolist()} for w in (swing, twist, tilted, still)]
    res = client.post("/v1/imu/windows", json={"windows": windows}).json()["results"]
    assert [r["turns_about_vertical"] for r in res] == [False, True, True, False]
    assert [r["moving"] for r in res] == [True, True, True, False]
    sensors = [{"sensor_id": "a", "windows": windows}, {"sensor_id": "b", "windows": windows[:1]}]
    out = client.post("/v1/imu/assign", json={"sensors": sensors}).json()["sensors"]
    assert [s["moving_windows_turning_about_vertical"] for s in out] == [2, 0]


def test_no_model_is_503_and_api_key_is_enforced(tmp_path: Path) -> None:
    with TestClient(create_app(Settings(models_dir=tmp_path))) as c:
        r = c.post("/v1/imu/windows", json={"windows": [_window()]})
        assert r.status_code == 503 and "no i2s_assignment model" in r.text
        assert c.get("/ready").status_code == 503
    root = tmp_path / "m"
    write_tiny_model(root, "i2s_assignment")
    with TestClient(create_app(Settings(models_dir=root, api_key="secret"))) as c:
        assert c.post("/v1/imu/windows", json={"windows": [_window()]}).status_code == 401
        ok = c.post("/v1/imu/windows", json={"windows": [_window()]}, headers={"X-API-Key": "secret"})
        assert ok.status_code == 200
        assert ok.json()["results"][0]["alignment"] is None  # no alignment model loaded


def test_a_tampered_model_is_refused_and_the_others_served(tiny_models: Path) -> None:
    (tiny_models / "i2s_alignment" / "0.0.1" / "model.onnx").write_bytes(b"corrupt")
    with TestClient(create_app(Settings(models_dir=tiny_models))) as c:
        assert set(c.get("/v1/models").json()) == {"i2s_assignment"}


def _binary(windows: list[dict]) -> bytes:
    return np.stack([np.array(w["samples"]) for w in windows]).astype("<f4").tobytes()


def test_binary_windows_equal_json_windows(client: TestClient) -> None:
    windows = [_window(), _window(rate=60.0)]
    windows[1]["samples"] = (np.array(windows[1]["samples"]) * 1.5).tolist()
    as_json = client.post("/v1/imu/windows", json={"windows": windows}).json()["results"]
    r = client.post(
        "/v1/imu/windows/binary",
        content=_binary(windows),
        headers={"content-type": "application/octet-stream"},
    )
    assert r.status_code == 200, r.text
    as_binary = r.json()["results"]
    for a, b in zip(as_json, as_binary, strict=True):
        assert a["segment"] == b["segment"]
        np.testing.assert_allclose(list(a["probabilities"].values()), list(b["probabilities"].values()), atol=1e-5)
        np.testing.assert_allclose(a["alignment"]["q_segment_imu"], b["alignment"]["q_segment_imu"], atol=1e-5)
    slow = _window(214, 100.0)
    scaled = np.array(slow["samples"]) * np.array([1 / 9.80665] * 3 + [np.degrees(1.0)] * 3)
    r = client.post(
        "/v1/imu/windows/binary?sample_rate_hz=100&samples_per_window=214&acc_unit=g&gyr_unit=deg/s&segment=Pelvis",
        content=scaled.astype("<f4").tobytes(),
    )
    assert r.status_code == 200, r.text
    ref = client.post("/v1/imu/windows", json={"windows": [{**slow, "segment": "Pelvis"}]}).json()["results"][0]
    np.testing.assert_allclose(
        list(ref["probabilities"].values()), list(r.json()["results"][0]["probabilities"].values()), atol=1e-4
    )
    assert r.json()["results"][0]["alignment"]["segment"] == "Pelvis"


@pytest.mark.parametrize(
    "query, body, fragment",
    [
        ("", b"", "got 0 bytes"),
        ("", b"\0" * (128 * 24 + 4), "3076 bytes"),
        ("?samples_per_window=100", b"\0" * (100 * 24), "128 samples, got 100"),
        ("?sample_rate_hz=5", b"\0" * (128 * 24), "sample_rate_hz: Input should be greater than or equal to 10"),
        ("?acc_unit=ft", b"\0" * (128 * 24), "acc_unit"),
        ("?segment=Head", b"\0" * (128 * 24), "segment"),
        ("", np.full((2, 128, 6), np.nan, "<f4").tobytes(), "window 0: samples must be finite"),
        (
            "",
            np.full((2, 128, 6), -3e6, "<f4").tobytes(),
            "window 0: samples must lie in [-1e+06, 1e+06] (in their unit), got 3e+06",
        ),
    ],
)
def test_bad_binary_bodies_are_422_with_a_message(client: TestClient, query: str, body: bytes, fragment: str) -> None:
    r = client.post("/v1/imu/windows/binary" + query, content=body)
    assert r.status_code == 422
    assert fragment in r.text


def test_openapi_documents_every_endpoint_with_examples(client: TestClient) -> None:
    import json
    import re

    from service.api.schemas import (
        AssignRequest,
        AssignResponse,
        FlexRequest,
        FlexResponse,
        PoseImuRequest,
        PoseImuResponse,
        WindowsRequest,
        WindowsResponse,
    )

    spec = client.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]

    def has_example(node: dict) -> bool:
        text = json.dumps(node)
        refs = [r.split("/")[-1] for r in re.findall(r'"\$ref": "([^"]+)"', text)]
        return "example" in text or any("example" in json.dumps(schemas[r]) for r in refs)

    for path, operations in spec["paths"].items():
        for method, op in operations.items():
            assert has_example(op["responses"]["200"]), f"{method} {path}: no response example"
            if "requestBody" in op:
                assert has_example(op["requestBody"]), f"{method} {path}: no request example"
    # The examples are valid bodies.
    bodies = (WindowsRequest, WindowsResponse, AssignRequest, AssignResponse, FlexRequest, FlexResponse)
    for model in (*bodies, PoseImuRequest, PoseImuResponse):
        for example in model.model_config["json_schema_extra"]["examples"]:
            model.model_validate(example)


@pytest.mark.parametrize(
    "body",
    ['"\\ud800"', '{"windows": [{"samples": [[0, 0, 9.8, 0, 0, 0]], "segment": "\\udfff"}]}', '{"\\ud800": 1}'],
)
def test_lone_surrogates_in_json_get_a_422_not_a_500(client: TestClient, body: str) -> None:
    """Valid JSON can escape a lone UTF-16 surrogate, which UTF-8 cannot encode; the 422 echoes it escaped."""
    r = client.post("/v1/imu/windows", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert r.json()["detail"]


@pytest.mark.parametrize("value", [True, "1.5"])
def test_samples_are_numbers_not_booleans_or_strings(client: TestClient, value) -> None:
    """JSON integers are numbers; true and "1.5" are refused with where they are, never coerced to 1.0 and 1.5."""
    rows = [[0, 0, 9.81, 0.1, 0.0, 0.0] for _ in range(128)]
    rows[7][2] = value
    r = client.post("/v1/imu/windows", json={"windows": [{"samples": rows}]})
    assert r.status_code == 422
    assert r.json()["errors"][0]["loc"][-3:] == ["samples", 7, 2], r.json()
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_json({"type": "start", "sensors": [{"sensor_id": "a"}]})
        assert ws.receive_json()["type"] == "started"
        ws.send_json({"type": "samples", "sensor_id": "a", "seq": 0, "samples": rows[:8]})
        message = ws.receive_json()
    assert message["type"] == "error" and "samples.7.2" in message["detail"] and message["close_code"] == 1008


def test_the_landing_page_links_the_docs_models_and_mlflow_ui(client: TestClient) -> None:
    r = client.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    for href in ("/docs", "/v1/models", "/metrics", "http://127.0.0.1:5000"):
        assert f'href="{href}"' in r.text
    assert "<td>i2s_assignment</td>" in r.text  # the loaded models


def test_the_landing_page_does_not_list_models_behind_an_api_key(tiny_models: Path) -> None:
    with TestClient(create_app(Settings(models_dir=tiny_models, api_key="k"))) as c:
        r = c.get("/")
    assert r.status_code == 200 and "i2s_assignment" not in r.text and "X-API-Key" in r.text


def test_the_api_docs_work_with_no_network(client: TestClient) -> None:
    """/docs loads the Swagger UI from the service package, not from a CDN."""
    page = client.get("/docs")
    assert page.status_code == 200
    assert "cdn" not in page.text and "https://" not in page.text
    assets = re.findall(r"""(?:src|href)=['"](/static/[^'"]+)['"]""", page.text)
    assert {"/static/swagger-ui/swagger-ui-bundle.js", "/static/swagger-ui/swagger-ui.css"} <= set(assets)
    for asset in assets:
        r = client.get(asset)
        assert r.status_code == 200 and len(r.content) > 500, asset
    assert "SwaggerUIBundle" in client.get("/static/swagger-ui/swagger-ui-bundle.js").text
    assert client.get("/openapi.json").json()["openapi"].startswith("3.1")  # Swagger UI 5 reads OpenAPI 3.1


def test_an_implausible_unit_is_answered_with_a_warning(client: TestClient) -> None:
    window = _window()
    assert client.post("/v1/imu/windows", json={"windows": [window]}).json()["warnings"] == []
    in_g = dict(window, samples=(np.array(window["samples"]) / 9.80665).tolist())  # g, declared as m/s²
    r = client.post("/v1/imu/windows", json={"windows": [in_g]})
    assert r.status_code == 200 and len(r.json()["results"]) == 1
    [warning] = r.json()["warnings"]
    assert warning.startswith("acc_unit:") and "'g'" in warning
    r = client.post("/v1/imu/assign", json={"sensors": [{"sensor_id": "s1", "windows": [in_g]}]})
    assert r.json()["warnings"][0].startswith("sensors[0] (s1): acc_unit:")


def _calibrated_client(tiny_models: Path, min_moving_windows: int = 3, session: bool = False) -> TestClient:
    """The tiny models, the assignment one with a confidence section that reads the vote share only; with
    ``session``, one that commits when the product of the sensors' probabilities reaches 0.99."""
    from service.core.assignment import CONFIDENCE_FEATURES, SESSION_FEATURES
    from service.core.manifest import ConfidenceSpec, SessionConfidenceSpec, read_manifest, write_manifest

    path = tiny_models / "i2s_assignment" / "0.0.1" / "manifest.json"
    manifest = read_manifest(path)
    product = SessionConfidenceSpec(features=list(SESSION_FEATURES), coef=[1.0, 0.0], intercept=0.0, threshold=0.99)
    manifest.confidence = ConfidenceSpec(
        features=list(CONFIDENCE_FEATURES),
        coef=[20.0, 0.0, 0.0],
        intercept=-10.0,
        threshold=0.99,
        min_moving_windows=min_moving_windows,
        session=product if session else None,
        fitted_on="a test",
    )
    write_manifest(manifest, path)
    return TestClient(create_app(Settings(models_dir=tiny_models)))


def test_assign_carries_a_calibrated_probability_and_a_status(client: TestClient, tiny_models: Path) -> None:
    """Without calibration the answer says so; with it, each sensor gets the calibrated probability and the session
    commits (``assigned``) only when every assigned sensor reaches the threshold on enough moving windows."""
    one = [{"sensor_id": "a", "windows": [_window()] * 4}]
    plain = client.post("/v1/imu/assign", json={"sensors": one}).json()
    assert plain["status"] == "uncalibrated" and plain["sensors"][0]["p_correct"] is None
    with _calibrated_client(tiny_models) as calibrated:
        got = calibrated.post("/v1/imu/assign", json={"sensors": one}).json()
        assert got["status"] == "assigned", got
        assert got["sensors"][0]["p_correct"] == pytest.approx(1.0 / (1.0 + np.exp(-10.0)))  # all 4 votes agree
        assert got["sensors"][0]["committed"] is True and plain["sensors"][0]["committed"] is None
        few = calibrated.post("/v1/imu/assign", json={"sensors": [{"sensor_id": "a", "windows": [_window()] * 2}]})
        assert few.json()["status"] == "not_enough_walking"  # 2 moving windows < 3
        assert few.json()["sensors"][0]["committed"] is False
        # identical data on three sensors: the two that the one-to-one answer moved off their windows' favourite
        # have no vote for their segment, so the session does not commit
        three = [{"sensor_id": f"s{k}", "windows": [_window()] * 4} for k in range(3)]
        out = calibrated.post("/v1/imu/assign", json={"sensors": three}).json()
        assert out["status"] == "not_enough_walking"
        assert sorted(round(s["p_correct"], 4) for s in out["sensors"]) == [0.0, 0.0, 1.0]
        # the one sure sensor is committed on its own while the session waits for the others
        assert [s["committed"] for s in out["sensors"]] == [s["p_correct"] > 0.99 for s in out["sensors"]]
        assert sum(s["committed"] for s in out["sensors"]) == 1
        still = [{"sensor_id": "a", "windows": [_window() | {"samples": [[0, 0, 9.81, 0, 0, 0]] * 128}] * 4}]
        assert calibrated.post("/v1/imu/assign", json={"sensors": still}).json()["status"] == "not_enough_walking"
        assert got["p_all_correct"] is None  # calibrated per sensor only
    with _calibrated_client(tiny_models, session=True) as by_session:
        got = by_session.post("/v1/imu/assign", json={"sensors": one}).json()
        assert got["status"] == "assigned" and got["p_all_correct"] == pytest.approx(got["sensors"][0]["p_correct"])
        out = by_session.post("/v1/imu/assign", json={"sensors": three}).json()
        assert out["status"] == "not_enough_walking" and out["p_all_correct"] < 1e-6


def _streamed_assignments(client: TestClient, sensors: int) -> list[dict]:
    """The ``assignment`` messages of a stream whose ``sensors`` all send the same 20 hops of a smooth signal."""
    t = np.arange(16 * 20) / 60.0
    x = np.stack([np.sin(t), np.cos(t), 9.81 + 0 * t, 2 * np.sin(3 * t), 0 * t, np.cos(2 * t)], axis=1)
    out = []
    with client.websocket_connect("/v1/stream") as ws:
        ws.send_text(json.dumps({"type": "start", "sensors": [{"sensor_id": f"s{k}"} for k in range(sensors)]}))
        assert json.loads(ws.receive_text())["type"] == "started"
        for seq in range(0, len(x), 16):
            for k in range(sensors):
                ws.send_bytes(encode_binary(k, seq, x[seq : seq + 16]))
        ws.send_text(json.dumps({"type": "stop"}))
        while True:
            try:
                m = json.loads(ws.receive_text())
            except WebSocketDisconnect:
                break
            if m["type"] == "assignment":
                out.append(m)
    return out


def test_the_streams_assignment_message_carries_the_calibrated_answer(tiny_models: Path) -> None:
    with _calibrated_client(tiny_models) as calibrated:
        messages = _streamed_assignments(calibrated, 1)
    statuses = [(m["sensors"][0]["windows"], m["status"], m["sensors"][0]["p_correct"]) for m in messages]
    assert statuses and statuses[-1][1] == "assigned" and statuses[-1][2] > 0.99
    assert messages[-1]["sensors"][0]["committed"] is True
    assert all(not m["sensors"][0]["committed"] for m in messages if m["sensors"][0]["windows"] < 3)
    assert all(status == "not_enough_walking" for n, status, _ in statuses if n < 3)


def test_the_streams_assignment_message_carries_the_probability_that_all_is_right(tiny_models: Path) -> None:
    with _calibrated_client(tiny_models, session=True) as calibrated:
        last = _streamed_assignments(calibrated, 2)[-1]  # the same readings on both: one of them cannot be right
    assert last["status"] == "not_enough_walking"
    assert last["p_all_correct"] == pytest.approx(np.prod([s["p_correct"] for s in last["sensors"]]))
    assert last["p_all_correct"] < 0.01


@pytest.mark.parametrize(
    ("body", "fragment"),
    [
        (b'{"windows": "\xff\xfe"}', "not UTF-8 JSON"),
        (b"[" * 100_000 + b"]" * 100_000, "too deeply"),
        (b'{"windows": [{"samples": [[' + b"9" * 5000 + b", 0, 9.8, 0, 0, 0]]}]}", "too many digits"),
    ],
    ids=["invalid utf-8", "deep nesting", "a 5000-digit integer"],
)
def test_a_body_json_cannot_read_says_why(client: TestClient, body: bytes, fragment: str) -> None:
    """Bodies that orjson and then json refuse for reasons other than JSON syntax get a 400 that says which, not
    FastAPI's bare "There was an error parsing the body"."""
    for route in ("/v1/imu/windows", "/v1/imu/assign", "/v1/pose/imu", "/v1/pose/flex"):
        r = client.post(route, content=body, headers={"content-type": "application/json"})
        assert r.status_code == 400 and fragment in r.json()["detail"], (route, r.status_code, r.text[:200])


@pytest.mark.parametrize(
    "content_type", ["text/plain", "application/x-www-form-urlencoded", "application/octet-stream", None]
)
def test_a_json_body_sent_as_another_media_type_is_named(client: TestClient, content_type: str) -> None:
    """FastAPI reads a body as JSON only when its Content-Type says JSON; any other type, or none, failed as
    "body: Input should be a valid dictionary". It is a 415 that names the type sent and the one expected."""
    body = b'{"windows": [{"samples": [[0, 0, 9.8, 0, 0, 0]]}]}'
    for route in ("/v1/imu/windows", "/v1/imu/assign", "/v1/pose/imu", "/v1/pose/flex"):
        r = client.post(route, content=body, headers={"content-type": content_type} if content_type else {})
        assert r.status_code == 415, (route, r.status_code, r.text[:200])
        assert r.json()["detail"] == (
            f"this route takes a JSON body (Content-Type: application/json); got {content_type or 'no Content-Type'}"
        )
    for declared in ("application/json; charset=utf-8", "application/vnd.wearmocap+json"):
        r = client.post("/v1/imu/windows", content=body, headers={"content-type": declared})
        assert r.status_code == 422 and "samples" in r.json()["detail"], (declared, r.text[:200])  # read as JSON
    r = client.post("/v1/imu/windows")  # no body at all: the body is missing, whatever the header says
    assert r.status_code == 422 and r.json()["detail"] == "body: Field required"
