"""What a person sees of a run and a model version in the MLflow UI: a name that says what the run is (recipe,
held-out fold, warm start, the versions it shipped as), a one-line description, experiments that open on their
training runs, and registry versions tagged with the version they shipped as.

The same rule names a run when it is trained, when it ships and when the snapshot is restored, from the run's
own params and tags, so that names never drift from what was logged.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping

from mlflow.entities import Run
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

NOTE_TAG = "mlflow.note.content"  # the run's or the experiment's description in the UI
RUN_NAME_TAG = "mlflow.runName"
EXPERIMENT_KIND_TAG = "mlflow.experimentKind"  # without it, MLflow 3 opens an experiment on its GenAI traces
SHIPPED_TAG = "shipped_as"

EXPERIMENTS = {
    "i2s": "Which body segment each IMU is on and how it is rotated there (Zimmermann et al. 2018), from IMU data "
    "simulated on CMU motion capture; one run per recipe and held-out subject.",
    "pose": "Full-body pose from sparse IMUs (Zheng et al. 2021; Vlutters 2016), from IMU data simulated on CMU and "
    "Bandai-Namco motion capture (CC BY-NC 4.0).",
    "flex": "Joint angles from resistive flex sensors (Chen et al. 2024), on a simulated flex-sensor suit driven by "
    "motion capture.",
    "flex_capacitive": "Knee flexion from the capacitive sleeves of a real subject (capacitive_sub01).",
    "pose_placement": "Where to put N IMUs for pose (Zheng et al. 2021 §6: mRMR over the maximal information "
    "coefficient between positions' measurements), on the training clips of a pose config.",
}
TASKS = {
    "assignment": "I2S assignment",
    "alignment": "I2S alignment",
    "imu_pose_velocity": "the pelvis velocity of the body's translation (TransPose 2021)",
}


def describe_experiment(client: MlflowClient, experiment_id: str, name: str) -> None:
    """Open on the training runs, with a one-line description where the experiment is one of ours."""
    client.set_experiment_tag(experiment_id, EXPERIMENT_KIND_TAG, "custom_model_development")
    if name in EXPERIMENTS:
        client.set_experiment_tag(experiment_id, NOTE_TAG, EXPERIMENTS[name])


def run_title(params: Mapping[str, str], tags: Mapping[str, str], shipped: list[str]) -> str:
    """``i2s_assignment · held out cmu_07 · from 1.8.0 · shipped 1.10.0``: recipe, fold, start, versions."""
    recipe = params.get("name") or tags.get(RUN_NAME_TAG, "run").split(" · ")[0]  # a title's first part, again
    parts = [recipe]
    held_out = _listed(params.get("data.test_subjects"))
    if "calibrated_from" in tags:  # training.i2s.calibration: the confidence fitted on a real-loso run's folds
        parts.append(f"fitted on the leave-one-person-out run {tags['calibrated_from'][:8]}")
    elif tags.get("real_loso") == "summary":
        parts.append("leave one person out, the summary")
    elif "real_loso_held_out" in tags:
        parts.append(f"held out {tags['real_loso_held_out']}")
    elif held_out:
        parts.append("held out " + ", ".join(held_out))
    real = _listed(params.get("data.real_train_recordings"))
    if real and "real_loso_held_out" not in tags:  # a fold trains on every other person's
        parts.append(f"+ {len(real)} real recordings")
    if _own(params):  # a pose run on the user's own motion capture (data.own)
        parts.append("+ own mocap")
    start = _start(params, tags)
    if start:
        parts.append(f"from {start}")
    if teacher := _teacher(params):
        parts.append(f"taught by {teacher}")
    if shipped:
        parts.append("shipped " + ", ".join(shipped))
    return " · ".join(parts)


def run_description(params: Mapping[str, str], tags: Mapping[str, str], shipped: list[str]) -> str:
    """One line: the task, the config, what was held out, the warm start, where it shipped, and any note."""
    task = TASKS.get(tags.get("task", params.get("task", "")), params.get("task") or tags.get("task") or "")
    recipe = params.get("name") or tags.get(RUN_NAME_TAG, "")
    words = [f"{task}: " if task else "", f"config {recipe}" if recipe else "a run"]
    held_out = _listed(params.get("data.test_subjects"))
    if held_out:
        words.append(f", held-out subjects {', '.join(held_out)}")
    real = _listed(params.get("data.real_train_recordings"))
    if real:
        words.append(f", fine-tuned on {len(real)} real recordings")
    if own := _own(params):
        also = "" if params.get("data.own.share") == "1.0" else "also "
        words.append(f", trained {also}on own motion capture ({own})")
    if start := _start(params, tags):
        words.append(f", warm start from {start}")
    if teacher := _teacher(params):
        words.append(f", distilled from {teacher}")
    if shipped:
        words.append(f"; shipped as {', '.join(shipped)}")
    if tags.get("note"):
        words.append(f". {tags['note']}")
    return "".join(words) + ("" if words[-1].endswith(".") else ".")


def label_run(client: MlflowClient, run_id: str, shipped: list[str] | None = None, run: Run | None = None) -> str:
    """Name and describe a run in the UI by the rule above, writing the tags that change; ``shipped``: versions it
    shipped as (else its tag); ``run``: the run as already fetched."""
    run = run or client.get_run(run_id)
    labels = run_labels(run.data.params, run.data.tags, shipped)
    for key, value in labels.items():
        if run.data.tags.get(key) != value:
            client.set_tag(run_id, key, value)
    return labels[RUN_NAME_TAG]


def run_labels(params: Mapping[str, str], tags: Mapping[str, str], shipped: list[str] | None = None) -> dict[str, str]:
    """The tags that name and describe a run of these params and tags (``label_run``; a restore sets them when it
    creates the run)."""
    versions = shipped if shipped is not None else [v for v in tags.get(SHIPPED_TAG, "").split(", ") if v]
    labels = {SHIPPED_TAG: ", ".join(versions)} if versions else {}
    labels[RUN_NAME_TAG] = run_title(params, tags, versions)
    labels[NOTE_TAG] = run_description(params, tags, versions)
    return labels


def label_version(client: MlflowClient, name: str, version: str, shipped: list[str]) -> None:
    """Show the shipped version(s) in the registry's version list (a tag) and as the version's description."""
    if not shipped:
        return
    client.set_model_version_tag(name, version, SHIPPED_TAG, ", ".join(shipped))
    folders = ", ".join(f"onnx_models/{name}/{v}" for v in shipped)
    client.update_model_version(name, version, description=f"Shipped as {folders}.")


def _listed(value: str | None) -> list[str]:
    """A list param as logged (``"['cmu_07']"``), or []."""
    if not value or value == "None":
        return []
    try:
        parsed = ast.literal_eval(value)
    except (ValueError, SyntaxError):
        return [value]
    return [str(v) for v in parsed] if isinstance(parsed, list | tuple) else [str(parsed)]


def _start(params: Mapping[str, str], tags: Mapping[str, str]) -> str:
    """The warm start: a shipped version (``1.8.0``), an ensemble, or a run (its first 8 characters)."""
    onnx_dir = tags.get("init_from_onnx") or params.get("train.init_from_onnx")
    if onnx_dir and onnx_dir != "None":
        return onnx_dir.rstrip("/").rsplit("/", 1)[-1]
    if tags.get("ensemble_of"):
        return "mean of " + " and ".join(p.rstrip("/").rsplit("/", 1)[-1] for p in tags["ensemble_of"].split(","))
    if tags.get("init_from_run"):
        return f"run {tags['init_from_run'][:8]}"
    return ""


def _own(params: Mapping[str, str]) -> str:
    """The folder of a pose run's own motion capture (``data.own.path``: its last part), or ""."""
    path = params.get("data.own.path")
    return path.rstrip("/").rsplit("/", 1)[-1] if path and path != "None" else ""


def _teacher(params: Mapping[str, str]) -> str:
    """The shipped version a run was distilled from (``train.distill_from``), or ""."""
    teacher = params.get("train.distill_from")
    return teacher.rstrip("/").rsplit("/", 1)[-1] if teacher and teacher != "None" else ""


def record_shipped(client: MlflowClient, run_id: str, name: str, version: str) -> None:
    """A run just shipped as ``name/version``: add the version to its name and description, and tag its registered
    versions with it."""
    run_id = _in_this_store(client, run_id)
    if run_id is None:
        return  # trained in another store and not restored here: nothing to label
    tags = client.get_run(run_id).data.tags
    shipped = [v for v in tags.get(SHIPPED_TAG, "").split(", ") if v]
    if version not in shipped:
        shipped.append(version)
    label_run(client, run_id, shipped)
    for registered in client.search_model_versions(f"name='{name}' and run_id='{run_id}'"):
        label_version(client, name, registered.version, shipped)


def _in_this_store(client: MlflowClient, run_id: str) -> str | None:
    """The run itself, or the run restored from it (``restored_from_run_id``), or None."""
    try:
        return client.get_run(run_id).info.run_id
    except MlflowException:
        pass
    experiments = [e.experiment_id for e in client.search_experiments()]
    runs = client.search_runs(experiments, f"tags.restored_from_run_id = '{run_id}'", max_results=1)
    return runs[0].info.run_id if runs else None


def label_unlabelled(client: MlflowClient) -> int:
    """Describe every experiment, and name and describe the runs that have no description yet (runs of older
    code, or of jobs that stopped early); the number of runs labelled."""
    experiments = client.search_experiments()
    for e in experiments:
        describe_experiment(client, e.experiment_id, e.name)
    ids = [e.experiment_id for e in experiments]
    runs = client.search_runs(ids, max_results=10_000) if ids else []
    unlabelled = [r for r in runs if NOTE_TAG not in r.data.tags]
    for run in unlabelled:
        label_run(client, run.info.run_id)
    return len(unlabelled)
