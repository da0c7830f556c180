"""``champion`` moves only on a win on the same evaluation, with scores compared as the registry keeps them."""

from __future__ import annotations

from pathlib import Path

import mlflow
import pytest
from mlflow.tracking import MlflowClient

from training.tracking import CHAMPION, maybe_promote

NAME = "promotion_test"
DIGEST = "118c8db71bae1df1f9a1"


@pytest.fixture
def registry(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> MlflowClient:
    """An embedded sqlite store with one registered model and four versions."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    client = MlflowClient()
    client.create_registered_model(NAME)
    for _ in range(4):
        client.create_model_version(NAME, source=str(tmp_path))
    return client


def _champion(client: MlflowClient) -> str:
    return str(client.get_model_version_by_alias(NAME, CHAMPION).version)


def test_a_tie_does_not_move_champion_even_when_the_tag_rounds_down(registry: MlflowClient) -> None:
    """1.9.0 tied 1.6.0 at 22,399 of 22,400 windows (0.99995536); the champion's tag keeps 0.999955, and the
    unrounded score used to beat it."""
    tie = 22_399 / 22_400
    assert maybe_promote(NAME, "1", "accuracy", tie, True, DIGEST)
    assert not maybe_promote(NAME, "2", "accuracy", tie, True, DIGEST)
    assert _champion(registry) == "1"
    assert not maybe_promote(NAME, "3", "accuracy", 1.0, True, "another evaluation")  # not comparable
    assert _champion(registry) == "1"
    # and the version says so, rather than looking like a loss
    assert registry.get_model_version(NAME, "3").tags["not_compared"] == "champion v1 has another eval_digest"
    assert maybe_promote(NAME, "4", "accuracy", 1.0, True, DIGEST)
    assert _champion(registry) == "4"


def test_lower_is_better_for_angle_errors(registry: MlflowClient) -> None:
    assert maybe_promote(NAME, "1", "mean_angle_error_deg", 1.7176161, False, DIGEST)
    assert not maybe_promote(NAME, "2", "mean_angle_error_deg", 1.7176159, False, DIGEST)  # equal at 6 decimals
    assert maybe_promote(NAME, "3", "mean_angle_error_deg", 1.70, False, DIGEST)
    assert _champion(registry) == "3"


def test_a_champion_chosen_on_other_grounds_carries_its_reason(registry: MlflowClient) -> None:
    """A version that loses on the test score becomes champion only with a written reason, tagged on it."""
    from training.tracking import make_champion

    assert maybe_promote(NAME, "1", "mean_angle_error_deg", 1.716, False, DIGEST)
    assert not maybe_promote(NAME, "2", "mean_angle_error_deg", 1.721, False, DIGEST)
    with pytest.raises(ValueError, match="reason"):
        make_champion(NAME, "2", "  ")
    assert _champion(registry) == "1"
    make_champion(NAME, "2", "validation within 0.2 degrees, a third of the cost")
    assert _champion(registry) == "2"
    assert registry.get_model_version(NAME, "2").tags["champion_by_decision"].startswith("validation within")
