"""MLflow set-up: an embedded sqlite store in the working directory unless a tracking URI is set."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import mlflow
import numpy as np
import onnx
from mlflow.models import ModelSignature, infer_signature
from mlflow.models.model import ModelInfo
from mlflow.tracking import MlflowClient
from mlflow.types import Schema
from mlflow.types import TensorSpec as MlflowTensorSpec

from service.core.manifest import MLMODEL_METADATA_KEY, Manifest, TensorSpec
from training.run_labels import describe_experiment

log = logging.getLogger(__name__)

CHAMPION = "champion"


def default_tracking_uri() -> str:
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{Path.cwd() / 'mlflow.db'}"


def setup_tracking(experiment: str) -> str:
    """Point MLflow at the store and create the experiment where it is missing, its artifacts where the store keeps
    them (the embedded store: ``./mlruns/<experiment id>``, MLflow's default; a server: its artifact root)."""
    uri = default_tracking_uri()
    mlflow.set_tracking_uri(uri)
    found = mlflow.set_experiment(experiment)  # creates it where missing
    describe_experiment(MlflowClient(), found.experiment_id, experiment)
    return uri


def log_onnx_model(
    proto: onnx.ModelProto,
    golden: dict[str, np.ndarray],
    manifest: Manifest,
    input_key: str | None = None,
    input_example: bool = True,
) -> ModelInfo:
    """Log the active run's ONNX model with its signature and, with ``input_example``, an input example (from the
    golden pair, keyed by the model's first input: ``imu`` for the I2S models, ``features`` for pose, ``counts`` for
    flex; a streaming graph's state inputs, ``h0`` and ``c0``, as the zeros a stream starts from). The manifest rides
    in the MLmodel metadata, so the service can serve the model straight from the registry."""
    input_key = input_key or manifest.inputs[0].name
    example: np.ndarray | dict[str, np.ndarray] = golden[input_key][:1]
    signature = infer_signature(golden[input_key], golden["expected"])
    if len(manifest.inputs) > 1:  # a streaming graph: MLflow takes its several inputs by name, as the manifest has them
        state = {
            s.name: np.zeros([1 if d == "batch" else d for d in s.shape], np.float32)
            for s in manifest.inputs
            if s.name != input_key
        }
        example = {input_key: example, **state}
        signature = ModelSignature(_schema(manifest.inputs), _schema(manifest.outputs))
    return mlflow.onnx.log_model(
        onnx_model=proto,
        name="model",
        signature=signature,
        # MLflow runs the model on its input example to check it (seconds per model): a restore, logging files
        # whose outputs their golden pair fixes, leaves the example out (the signature stays)
        input_example=example if input_example else None,
        save_as_external_data=False,
        metadata={MLMODEL_METADATA_KEY: manifest.model_dump(mode="json")},
        # what MLflow would infer by importing the model in a subprocess (about 2 s per model, most of a restore)
        pip_requirements=onnx_model_requirements(),
    )


def download_onnx(model_uri: str, dst: str | Path) -> Path:
    """The ONNX file of a logged model (a run's ``model_uri`` tag), downloaded under ``dst``."""
    return next(Path(mlflow.artifacts.download_artifacts(model_uri, dst_path=str(dst))).rglob("*.onnx"))


def _schema(specs: list[TensorSpec]) -> Schema:
    """MLflow's tensor schema of a manifest's inputs or outputs: named, their symbolic dimensions variable."""
    return Schema(
        [
            MlflowTensorSpec(np.dtype(s.dtype), tuple(d if isinstance(d, int) else -1 for d in s.shape), s.name)
            for s in specs
        ]
    )


def onnx_model_requirements() -> list[str]:
    """A logged ONNX model's pip requirements, pinned to this environment's versions: what MLflow's inference finds
    when it loads such a model (mlflow, numpy, onnx, onnxruntime)."""
    return [f"mlflow=={mlflow.__version__}", f"numpy=={np.__version__}", *mlflow.onnx.get_default_pip_requirements()]


def maybe_promote(
    name: str, version: str, metric: str, value: float, higher_is_better: bool, evaluation_digest: str
) -> bool:
    """Move the ``champion`` alias to ``version`` only if it beats the champion on the same evaluation.

    Versions carry their evaluation's digest and score as tags; a champion evaluated on other data
    is not comparable, so the alias stays where it is (and the caller logs why).
    """
    client = MlflowClient()
    value = float(_score_tag(value))  # compared at the precision the champion's score is kept in (its tag)
    _tag_evaluation(client, name, version, metric, value, evaluation_digest)
    try:
        champion = client.get_model_version_by_alias(name, CHAMPION)
    except mlflow.exceptions.MlflowException:
        champion = None
    if champion is not None:
        if champion.tags.get("eval_digest") != evaluation_digest:
            log.warning(
                "%s version %s: not compared with champion version %s, which was evaluated on other data or another "
                "way (eval_digest %s, this one %s); the alias stays",
                name,
                version,
                champion.version,
                champion.tags.get("eval_digest"),
                evaluation_digest,
            )
            reason = f"champion v{champion.version} has another eval_digest"
            client.set_model_version_tag(name, version, "not_compared", reason)
            return False
        best = float(champion.tags[f"eval_{metric}"])
        if (value <= best) if higher_is_better else (value >= best):
            return False
    client.set_registered_model_alias(name, CHAMPION, version)
    return True


def make_champion(name: str, version: str, reason: str) -> None:
    """Move ``champion`` to ``version`` on a decision other than its test score, recorded as the version's tag
    ``champion_by_decision`` (a choice made on validation must not be re-made on the test figures)."""
    if not reason.strip():
        raise ValueError("a champion chosen against its test score needs the reason written down")
    client = MlflowClient()
    client.set_model_version_tag(name, version, "champion_by_decision", reason)
    client.set_registered_model_alias(name, CHAMPION, version)


def record_evaluation(name: str, run_id: str, metric: str, value: float, evaluation_digest: str) -> list[str]:
    """Tag the registered versions of ``run_id`` with a newer evaluation of the same model (``evaluate`` on its
    shipped float32 file), so that ``maybe_promote`` compares later versions with it on the same data."""
    client = MlflowClient()
    try:
        versions = client.search_model_versions(f"name='{name}' and run_id='{run_id}'")
    except mlflow.exceptions.MlflowException:
        return []
    for v in versions:
        _tag_evaluation(client, name, v.version, metric, value, evaluation_digest)
    return [v.version for v in versions]


def _tag_evaluation(client: MlflowClient, name: str, version: str, metric: str, value: float, digest: str) -> None:
    """The tags ``maybe_promote`` compares versions by: which evaluation, and the score on it."""
    client.set_model_version_tag(name, version, "eval_digest", digest)
    client.set_model_version_tag(name, version, f"eval_{metric}", _score_tag(value))


def _score_tag(value: float) -> str:
    """A score as tagged on a version. A tie must stay a tie: 0.99995536 is not a win over a champion tagged
    0.999955 with the same score."""
    return f"{value:.6f}"


def register_model(model_uri: str, name: str):
    """``mlflow.register_model``, numbered as the tracking snapshot numbers (``number_as_in_snapshot``): every task
    registers through this."""
    version = mlflow.register_model(model_uri, name)
    number_as_in_snapshot(MlflowClient(), name, str(version.version))
    return version


def number_as_in_snapshot(client: MlflowClient, name: str, version: str) -> None:
    """Give a version just registered in a restored store the snapshot's next number (``original_version``).

    A restore leaves out the versions whose model file does not ship, so the store numbers its versions 1, 2, …
    while the snapshot keeps the original numbers (1, 3, 4, …). Without the tag a new store version 5 would be
    exported as version 5, which the snapshot may already hold, and a later restore would point aliases at the
    wrong model.
    """
    versions = client.search_model_versions(f"name='{name}'")
    if not any("original_version" in v.tags for v in versions):
        return  # not a restored store: its numbers are the snapshot's
    taken = [int(v.tags.get("original_version", v.version)) for v in versions if str(v.version) != str(version)]
    client.set_model_version_tag(name, version, "original_version", str(max(taken) + 1))
