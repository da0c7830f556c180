"""A committed snapshot of the tracking store, so that a fresh clone's MLflow UI shows the runs behind the shipped
models instead of an empty dashboard.

``export_snapshot`` writes the finished runs of the local store (params, tags, every metric's history, the
datasets logged with ``log_input``, and the artifacts except the torch checkpoints) and the model registry
(versions, tags, aliases) to a folder: JSON plus the plots and evaluation files. ``restore_snapshot`` replays
them into any tracking store as new runs tagged ``restored_from_run_id`` (MLflow assigns run ids; the manifests
name the original ones), and re-registers every version whose float32 ONNX file ships in ``onnx_models/``
(the manifest names its run), with the original tags, the ``original_version`` and the aliases. A version whose
model file does not ship is reported and left out, never faked. Restoring twice adds nothing.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import mlflow
import numpy as np
import onnx
from mlflow.entities import Dataset, DatasetInput, InputTag, Metric, Param
from mlflow.exceptions import MlflowException
from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository
from mlflow.tracking import MlflowClient

from service.core.manifest import read_manifest, sha256_file
from service.inference.registry import version_key
from training.run_labels import RUN_NAME_TAG, SHIPPED_TAG, describe_experiment, label_run, label_version, run_labels
from training.tracking import log_onnx_model, setup_tracking

log = logging.getLogger(__name__)

RESTORED_TAG = "restored_from_run_id"
DERIVED_VERSION_TAGS = ("original_version", "model_dir", SHIPPED_TAG)  # written by each restore, not kept
ARCHIVE = "models"  # <snapshot>/models/<name>/<version>: shipped versions that are no longer served
SKIPPED_ARTIFACTS = {"checkpoint"}  # torch weights: large, and the ONNX files ship in onnx_models/
BATCH = 1000  # metrics per log_batch call, its limit (also 100 params, 100 tags); 500 made a restore 14 % slower
BULK_RUNS = 500  # runs per bulk history query (an SQL IN list; SQLite allows 32,766 variables)


@dataclass
class RestoreReport:
    runs_restored: int = 0
    runs_present: int = 0
    versions_registered: list[str] = field(default_factory=list)
    versions_without_model: list[str] = field(default_factory=list)


def export_snapshot(out_dir: Path, experiments: list[str]) -> int:
    """Write the FINISHED runs of ``experiments`` and the whole registry to ``out_dir``; returns the run count.

    Runs and versions that were themselves restored are written under their original run id and version, so
    that a snapshot of a restored store still matches the manifests."""
    client = MlflowClient()
    shutil.rmtree(out_dir / "artifacts", ignore_errors=True)  # no files of runs that are gone
    out_dir.mkdir(parents=True, exist_ok=True)
    ids = [e.experiment_id for name in experiments if (e := client.get_experiment_by_name(name)) is not None]
    runs = client.search_runs(ids, "attributes.status = 'FINISHED'", max_results=10_000, order_by=["start_time ASC"])
    records, origin = [], {}
    histories = _metric_histories(client, runs)
    for run in runs:
        rid = run.info.run_id
        origin[rid] = run.data.tags.get(RESTORED_TAG, rid)
        records.append(
            {
                "run_id": origin[rid],
                "experiment": client.get_experiment(run.info.experiment_id).name,
                "run_name": run.info.run_name,
                "start_time": run.info.start_time,
                "end_time": run.info.end_time,
                "params": run.data.params,
                "tags": {k: v for k, v in run.data.tags.items() if k != "model_uri"},  # model URIs are per store
                "metrics": {key: histories[rid, key] for key in run.data.metrics},
                "inputs": [
                    {
                        "name": d.dataset.name,
                        "digest": d.dataset.digest,
                        "source_type": d.dataset.source_type,
                        "source": d.dataset.source,
                        "schema": d.dataset.schema,
                        "profile": d.dataset.profile,
                        "tags": {t.key: t.value for t in d.tags},
                    }
                    for d in run.inputs.dataset_inputs
                ],
            }
        )
        # The run's artifact store directly: through ``runs:/`` URIs each download looks the run up again (8 times
        # slower, 2026-12-07: a third of an export of 367 runs)
        artifacts = get_artifact_repository(run.info.artifact_uri, tracking_uri=mlflow.get_tracking_uri())
        for top in artifacts.list_artifacts():
            if top.path not in SKIPPED_ARTIFACTS:
                artifacts.download_artifacts(top.path, str(_artifact_dir(out_dir, origin[rid])))
    registry = {}
    for model in client.search_registered_models():
        versions = sorted(client.search_model_versions(f"name='{model.name}'"), key=lambda v: int(v.version))
        original = {str(v.version): v.tags.get("original_version", str(v.version)) for v in versions}
        registry[model.name] = {
            "aliases": {alias: original[str(version)] for alias, version in model.aliases.items()},
            "versions": [
                {
                    "version": original[str(v.version)],
                    "run_id": origin.get(v.run_id) or _original_run_id(client, v.run_id),
                    "tags": {k: t for k, t in v.tags.items() if k not in DERIVED_VERSION_TAGS},
                }
                for v in versions
            ],
        }
    previous = out_dir / "registry.json"
    if previous.is_file():
        _keep_unrestored_versions(json.loads(previous.read_text()), registry, {r["run_id"] for r in records})
    (out_dir / "runs.json").write_text(json.dumps(records, indent=1, sort_keys=True) + "\n")
    previous.write_text(json.dumps(registry, indent=1, sort_keys=True) + "\n")
    return len(records)


def _metric_histories(client: MlflowClient, runs: list) -> dict[tuple[str, str], list[list]]:
    """(run id, key) → [[step, timestamp, value], …] in the order ``get_metric_history`` gives them (timestamp,
    step, value). A SQL store answers one query per metric key over all runs (as MLflow's own UI asks it), where
    one per run and key took half an export of 367 runs (42,700 queries, 67 s on two cores, 2026-12-07); any other
    store is asked one history at a time."""
    # no public accessor; MLflow's own server checks for the method the same way
    store = getattr(getattr(client, "_tracking_client", None), "store", None)
    keys: dict[str, list[str]] = {}
    for run in runs:
        for key in run.data.metrics:
            keys.setdefault(key, []).append(run.info.run_id)
    out: dict[tuple[str, str], list[list]] = {}
    for key, run_ids in keys.items():
        if hasattr(store, "get_metric_history_bulk"):
            for i in range(0, len(run_ids), BULK_RUNS):
                chunk = run_ids[i : i + BULK_RUNS]
                for rid in chunk:
                    out[rid, key] = []
                for m in store.get_metric_history_bulk(chunk, key, max_results=2**31 - 1):
                    out[m.run_id, key].append([m.step, m.timestamp, m.value])
        else:
            for rid in run_ids:
                out[rid, key] = [[m.step, m.timestamp, m.value] for m in client.get_metric_history(rid, key)]
    return out


def _original_run_id(client: MlflowClient, run_id: str) -> str:
    """The snapshot's id of a run that this export does not write (another experiment's)."""
    try:
        return client.get_run(run_id).data.tags.get(RESTORED_TAG, run_id)
    except MlflowException:  # a version whose run was deleted
        return run_id


def _keep_unrestored_versions(previous: dict, registry: dict, run_ids: set[str]) -> None:
    """Carry over the versions of the snapshot being replaced that a restore leaves out (their model file does not
    ship, ``RestoreReport.versions_without_model``) while their runs are still exported, with their aliases: so
    exporting a restored store does not drop them from the snapshot."""
    for name, old in previous.items():
        new = registry.setdefault(name, {"aliases": {}, "versions": []})
        present = {v["version"]: v["run_id"] for v in new["versions"]}
        for v in old["versions"]:
            if present.get(v["version"], v["run_id"]) != v["run_id"]:
                raise ValueError(
                    f"{name} v{v['version']}: the snapshot gives this number to run {v['run_id']}, the store to run "
                    f"{present[v['version']]}; tag the store's version with the snapshot's next number "
                    "(training.tracking.number_as_in_snapshot) and export again"
                )
        kept = [v for v in old["versions"] if v["version"] not in present and v["run_id"] in run_ids]
        new["versions"] = sorted(new["versions"] + kept, key=lambda v: int(v["version"]))
        kept_versions = {v["version"] for v in kept}
        for alias, version in old["aliases"].items():
            if version in kept_versions:
                new["aliases"].setdefault(alias, version)


def restore_snapshot(snapshot_dir: Path, models_dir: Path) -> RestoreReport:
    """Replay ``snapshot_dir`` into the current tracking store (see the module docstring)."""
    client = MlflowClient()
    report = RestoreReport()
    records = json.loads((snapshot_dir / "runs.json").read_text())
    registry = json.loads((snapshot_dir / "registry.json").read_text())
    restored = _restored_runs(client)
    model_dirs = shipped_model_dirs(models_dir, snapshot_dir)
    models = _shipped_float32_models(model_dirs)
    present_versions = {
        (mv.name, mv.tags.get("original_version")) for mv in client.search_model_versions(max_results=10_000)
    }
    registered = {  # the runs of the versions this restore registers (a run of two versions: one logged model)
        v["run_id"]
        for name, entry in registry.items()
        for v in entry["versions"]
        if (name, v["version"]) not in present_versions
    }
    shipped = _shipped_versions(model_dirs)
    logged: dict[str, str] = {}  # original run id → the model URI logged with its restored run
    experiments: dict[str, str] = {}  # name → id, each set up once
    present = dict(restored)  # labelled again below: a version may have shipped since their restore
    for record in records:
        if record["run_id"] in restored:
            report.runs_present += 1
            continue
        if record["experiment"] not in experiments:
            setup_tracking(record["experiment"])
            experiments[record["experiment"]] = client.get_experiment_by_name(record["experiment"]).experiment_id
        model_dir = models.get(record["run_id"]) if record["run_id"] in registered else None
        versions = shipped.get(record["run_id"], [])
        restored[record["run_id"]], model_uri = _restore_run(
            client, record, experiments[record["experiment"]], versions, snapshot_dir, model_dir
        )
        if model_uri:
            logged[record["run_id"]] = model_uri
        report.runs_restored += 1
    for name, entry in registry.items():
        _restore_registered_model(client, name, entry, restored, models, logged, report)
    _label(client, present, shipped)
    return report


def shipped_model_dirs(models_dir: Path, snapshot_dir: Path) -> list[Path]:
    """Every shipped version's folder: the served ones in ``models_dir`` and the archived ones in the snapshot."""
    return sorted(p.parent for root in (models_dir, snapshot_dir / ARCHIVE) for p in root.glob("*/*/manifest.json"))


def _shipped_versions(model_dirs: list[Path]) -> dict[str, list[str]]:
    """original run id → the versions it shipped as, oldest first."""
    shipped: dict[str, list[str]] = {}
    for model_dir in model_dirs:
        run_id = read_manifest(model_dir / "manifest.json").mlflow.get("run_id")
        if run_id:
            shipped.setdefault(run_id, []).append(model_dir.name)
    return {run_id: sorted(versions, key=version_key) for run_id, versions in shipped.items()}


def _label(client: MlflowClient, present: dict[str, str], shipped: dict[str, list[str]]) -> None:
    """Describe the experiments, name and describe the runs restored before (this restore's were named when it made
    them), and tag every registered version with the versions it shipped as."""
    experiments = client.search_experiments()
    for experiment in experiments:
        describe_experiment(client, experiment.experiment_id, experiment.name)
    ids = [e.experiment_id for e in experiments]
    found = client.search_runs(ids, f"tags.{RESTORED_TAG} != ''", max_results=10_000) if present else []
    runs = {r.info.run_id: r for r in found}
    for original, rid in present.items():
        label_run(client, rid, shipped.get(original, []), runs.get(rid))
    for model in client.search_registered_models():
        for mv in client.search_model_versions(f"name='{model.name}'"):
            original = client.get_run(mv.run_id).data.tags.get(RESTORED_TAG, mv.run_id) if mv.run_id else ""
            label_version(client, model.name, mv.version, shipped.get(original, []))


def restore_if_empty(snapshot_dir: Path, models_dir: Path) -> RestoreReport | None:
    """Restore only into a store with no runs at all (a fresh clone's); None if it has runs or there is no snapshot."""
    client = MlflowClient()
    experiments = [e.experiment_id for e in client.search_experiments()]
    if not (snapshot_dir / "runs.json").is_file() or client.search_runs(experiments, max_results=1):
        return None
    return restore_snapshot(snapshot_dir, models_dir)


def local_run_id(run_id: str) -> str:
    """The run a manifest names, in this store: the run itself if it is here, else the run restored from it.

    Manifests name the run ids of the store they were trained in; a store restored from the snapshot holds the same
    runs under new ids (``restored_from_run_id``).
    """
    client = MlflowClient()
    try:
        return client.get_run(run_id).info.run_id
    except MlflowException:
        pass
    restored = _restored_runs(client)
    if run_id not in restored:
        raise LookupError(
            f"run {run_id} is not in the tracking store {mlflow.get_tracking_uri()}, and no run here was restored "
            "from it: restore the committed runs with `python -m training.cli snapshot-restore`, or point "
            "MLFLOW_TRACKING_URI at the store it was trained in"
        )
    return restored[run_id]


def _artifact_dir(snapshot_dir: Path, run_id: str) -> Path:
    path = snapshot_dir / "artifacts" / run_id
    path.mkdir(parents=True, exist_ok=True)
    return path


def _restored_runs(client: MlflowClient) -> dict[str, str]:
    """original run id → run id in this store, for the runs restored before."""
    ids = [e.experiment_id for e in client.search_experiments()]
    runs = client.search_runs(ids, f"tags.{RESTORED_TAG} != ''", max_results=10_000) if ids else []
    return {r.data.tags[RESTORED_TAG]: r.info.run_id for r in runs}


def _shipped_float32_models(model_dirs: list[Path]) -> dict[str, Path]:
    """original run id → the float32 model dir it shipped as (the int8 files, and the files derived from a shipped one,
    are not registered: the registry holds what the run exported)."""
    found = {}
    for model_dir in model_dirs:
        manifest = read_manifest(model_dir / "manifest.json")
        derived = "quantization" in manifest.exporter or "derived_from" in manifest.exporter
        if not derived and manifest.mlflow.get("run_id"):
            found[manifest.mlflow["run_id"]] = model_dir
    return found


def _restore_run(
    client: MlflowClient,
    record: dict,
    experiment_id: str,
    shipped: list[str],
    snapshot_dir: Path,
    model_dir: Path | None,
) -> tuple[str, str | None]:
    """The restored run's id, and the URI of the model logged with it where ``model_dir`` holds its registered file.
    It is named and described as ``label_run`` would, for the versions it ``shipped`` as.

    The model is logged after the params (it takes the run's) and before the metrics: MLflow links a logged model to
    its run's metrics of step 0 by reading every metric's history back and writing those again (a third of a
    restore's time); logged first, the run has none yet, and the step-0 metrics are written once with the model's
    id: the same links. A run registered under two names gets one logged model for both versions. A run that fails
    half-way is deleted, so that the next restore makes it anew instead of counting it as restored."""
    tags = {**record["tags"], RESTORED_TAG: record["run_id"], "restored_from": "mlflow_snapshot/ (training.snapshot)"}
    tags |= run_labels(record["params"], {**tags, RUN_NAME_TAG: record["run_name"]}, shipped)
    run = client.create_run(experiment_id, start_time=record["start_time"], tags=tags, run_name=tags[RUN_NAME_TAG])
    rid = run.info.run_id
    try:
        params = [Param(k, v) for k, v in record["params"].items()]
        for i in range(0, len(params), 100):  # before the model, which takes the run's params
            client.log_batch(rid, params=params[i : i + 100])
        model_uri = model_id = None
        if model_dir is not None:
            model_uri, model_id = _log_shipped_model(rid, model_dir)
        metrics = [
            Metric(k, value, timestamp, step, model_id=model_id if step == 0 else None)
            for k, rows in record["metrics"].items()
            for step, timestamp, value in rows
        ]
        for i in range(0, len(metrics), BATCH):
            client.log_batch(rid, metrics=metrics[i : i + BATCH])
        datasets = [
            DatasetInput(
                Dataset(d["name"], d["digest"], d["source_type"], d["source"], d["schema"], d["profile"]),
                [InputTag(k, v) for k, v in d["tags"].items()],
            )
            for d in record["inputs"]
        ]
        if datasets:
            client.log_inputs(rid, datasets=datasets)
        artifacts = snapshot_dir / "artifacts" / record["run_id"]
        if artifacts.is_dir():
            client.log_artifacts(rid, str(artifacts))
        client.set_terminated(rid, "FINISHED", end_time=record["end_time"])
    except BaseException:
        client.delete_run(rid)
        raise
    return rid, model_uri


def _log_shipped_model(rid: str, model_dir: Path) -> tuple[str, str]:
    """Log the shipped ONNX file of ``model_dir`` with run ``rid`` (ending it); its URI and id."""
    mlflow.set_experiment(experiment_id=MlflowClient().get_run(rid).info.experiment_id)  # runs of several experiments
    with np.load(model_dir / "golden.npz") as z, mlflow.start_run(run_id=rid):
        manifest = read_manifest(model_dir / "manifest.json")
        info = log_onnx_model(onnx.load(str(model_dir / "model.onnx")), dict(z), manifest, None, False)
        mlflow.set_tag("model_uri", info.model_uri)
    return info.model_uri, info.model_id


def _restore_registered_model(
    client: MlflowClient,
    name: str,
    entry: dict,
    restored: dict[str, str],
    models: dict[str, Path],
    logged: dict[str, str],
    report: RestoreReport,
) -> None:
    shippable = [v for v in entry["versions"] if v["run_id"] in models and v["run_id"] in restored]
    try:
        client.get_registered_model(name)
    except mlflow.exceptions.MlflowException:
        if not shippable:  # no version has a model file here: no empty registered model in the UI
            report.versions_without_model += [f"{name} v{v['version']}" for v in entry["versions"]]
            return
        client.create_registered_model(name)
    # original version → version in this store, for the versions restored before
    new_version = {
        v.tags["original_version"]: v.version
        for v in client.search_model_versions(f"name='{name}'")
        if "original_version" in v.tags
    }
    for version in entry["versions"]:
        label = f"{name} v{version['version']}"
        model_dir = models.get(version["run_id"])
        if version["version"] in new_version:
            continue
        if model_dir is None or version["run_id"] not in restored:
            report.versions_without_model.append(label)
            continue
        rid = restored[version["run_id"]]
        model_uri = logged.get(version["run_id"])
        if model_uri is None:  # its run was restored before, without the model
            end_time = client.get_run(rid).info.end_time
            model_uri = logged[version["run_id"]] = _log_shipped_model(rid, model_dir)[0]
            client.set_terminated(rid, "FINISHED", end_time=end_time)  # the original end, not now
        tags = {**version["tags"], "original_version": version["version"], "model_dir": str(model_dir)}
        mv = client.create_model_version(name, model_uri, run_id=rid, tags=tags)
        new_version[version["version"]] = mv.version
        report.versions_registered.append(label)
    for alias, original in entry["aliases"].items():
        if original in new_version:
            client.set_registered_model_alias(name, alias, new_version[original])


def log_restore(report: RestoreReport) -> None:
    log.info(
        "tracking snapshot: %d runs restored (%d already there), registered %s; no shipped model file for %s",
        report.runs_restored,
        report.runs_present,
        ", ".join(report.versions_registered) or "nothing",
        ", ".join(report.versions_without_model) or "none",
    )


def restore_model(name: str, version: str, snapshot_dir: Path, models_dir: Path) -> list[Path]:
    """Copy the archived ``name/version`` (and, for an ensemble, its members) from the snapshot back into
    ``models_dir``, checking each file's sha256 against its manifest; the folders written, members first."""
    source = snapshot_dir / ARCHIVE / name / version
    if not (source / "manifest.json").is_file():
        archived = sorted(p.parent.name for p in (snapshot_dir / ARCHIVE / name).glob("*/manifest.json"))
        served = sorted(p.parent.name for p in (models_dir / name).glob("*/manifest.json"))
        raise LookupError(
            f"{name} {version} is not archived in {snapshot_dir / ARCHIVE}; archived: {archived or 'none'}, "
            f"in {models_dir}: {served or 'none'}"
        )
    manifest = read_manifest(source / "manifest.json")
    written = []
    for member in manifest.exporter.get("ensemble_of", []):  # "i2s_assignment/1.6.0": relative to the models root
        if not (models_dir / member / "manifest.json").is_file():
            written += restore_model(*str(member).split("/"), snapshot_dir, models_dir)
    if sha256_file(source / "model.onnx") != manifest.sha256:
        raise ValueError(f"{source / 'model.onnx'} does not match the sha256 of its manifest")
    target = models_dir / name / version
    if target.exists():
        raise FileExistsError(f"{target} exists")
    shutil.copytree(source, target)
    return [*written, target]


def archive_model(name: str, version: str, snapshot_dir: Path, models_dir: Path) -> Path:
    """Move a version that is no longer served from ``models_dir`` into the snapshot's archive; the new folder."""
    source, target = models_dir / name / version, snapshot_dir / ARCHIVE / name / version
    if not (source / "manifest.json").is_file():
        raise LookupError(f"{source} holds no shipped model")
    if target.exists():
        raise FileExistsError(f"{target} exists")
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(source, target)
    return target
