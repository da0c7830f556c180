"""The manifest's contract for a learned pelvis velocity (``imu_pose_velocity``): the shipped one holds, and a
manifest that would mislead the service about its tensors is refused with what was expected. Service code only."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.core.manifest import Evaluation, Manifest, read_manifest, with_evaluation
from service.inference.registry import newest_version_dir

SHIPPED = Path(__file__).resolve().parents[2] / "onnx_models" / "pose_full6_velocity"


def _newest() -> Path:
    newest = newest_version_dir(SHIPPED.parent, SHIPPED.name)
    assert newest is not None
    return newest


def _shipped() -> dict:
    return json.loads((_newest() / "manifest.json").read_text())


def test_the_shipped_velocity_manifest_holds_its_contract() -> None:
    raw = _shipped()
    m = Manifest.model_validate(raw)
    assert m.task == "imu_pose_velocity" and m.velocity is not None and m.velocity.sensors[0] == "Pelvis"
    assert 0.0 <= m.velocity.learned_share <= 1.0 and m.velocity.chosen_with.startswith("pose_full6 ")
    assert read_manifest(_newest() / "manifest.json").velocity is not None


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda m: m.pop("velocity"), "needs a 'velocity' section"),
        (lambda m: m["outputs"][0].update(shape=["batch", "frames", 2]), "returns (velocity, h, c)"),
        (lambda m: m["inputs"].pop(), "takes (features, h0, c0)"),
        (lambda m: m["inputs"][0].update(shape=["batch", "frames", 60]), "takes (features, h0, c0)"),
        (lambda m: m["velocity"].update(sensors=["Head", "Pelvis"]), "sensors start with Pelvis"),
        (lambda m: m["velocity"].update(feature_version="pelvis_relative_v0"), "this service computes"),
        (lambda m: m["velocity"].update(acc_scale_mps2=9.81), "this service computes"),
        (lambda m: m.update(sample_rate_hz=100.0), "at 60 Hz"),
        (lambda m: m["velocity"].update(learned_share=1.5), "less than or equal to 1"),
    ],
)
def test_a_velocity_manifest_that_misdescribes_its_model_is_refused(change, message: str) -> None:
    raw = _shipped()
    change(raw)
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Manifest.model_validate(raw)


def test_an_evaluation_scored_again_replaces_its_namesake_first_or_beside_the_one_named() -> None:
    """``with_evaluation``: a figure scored again takes its namesake's place at the top, or right after the
    evaluation ``after`` names (a figure beside the headline one), and no other evaluation moves or goes."""
    m = read_manifest(_newest() / "manifest.json")
    one = Evaluation(name="held out", command="c1", data="d", metrics={"x": 1.0})
    other = Evaluation(name="other", command="c2", data="d", metrics={"y": 2.0})
    m = m.model_copy(update={"evaluations": [one, other]})
    beside = Evaluation(name="held out, 5 sessions", command="c3", data="d", metrics={"x": 1.5})
    names = [e.name for e in with_evaluation(m, beside, after="held out").evaluations]
    assert names == ["held out", "held out, 5 sessions", "other"]
    again = with_evaluation(with_evaluation(m, beside, after="held out"), beside, after="held out")
    assert [e.name for e in again.evaluations] == names
    assert [e.name for e in with_evaluation(m, beside).evaluations] == ["held out, 5 sessions", "held out", "other"]
    assert [e.name for e in with_evaluation(m, beside, after="absent").evaluations][0] == "held out, 5 sessions"
    rescored = with_evaluation(m, one.model_copy(update={"metrics": {"x": 3.0}}))
    assert [e.metrics for e in rescored.evaluations] == [{"x": 3.0}, {"y": 2.0}]
