"""Flex experiments as MLflow runs: one per network of Chen et al. 2024 Table 5 (data, training, validation,
held-out subjects, robustness to ageing and to a replaced sensor, plots, ONNX with parity, registry), and one
summary run with the table and the bar chart. The validation subjects choose; the held-out subjects are reported.
"""

from __future__ import annotations

import hashlib
import json
import logging
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import mlflow
import numpy as np
import onnx
import pandas as pd
from mlflow.tracking import MlflowClient

from service.core.manifest import Evaluation, sha256_file
from service.inference.flex import FlexModel
from service.inference.registry import load_model
from training.config import flatten
from training.data.catalog import BANDAI_LICENCE, is_bandai_namco, mocap_entries
from training.flex.config import FlexConfig
from training.flex.data import FlexClip, WindowSet, clip_seed, clip_suit, flex_clip, window_set
from training.flex.evaluate import clip_metrics, flat_metrics, mean_pose_predictor
from training.flex.export import build_flex_manifest, export_flex_onnx, onnx_parity
from training.flex.simulate import AGEING_BEYOND, FLEX_RATE_HZ, draw_sensor, draw_suit, simulate_counts
from training.flex.train import FlexTrainResult, answer_mask, torch_predictor, train_flex
from training.plots import bars_png, curves_png, flex_learning_curve_png, traces_png
from training.pose.data import (
    build_motions,
    dataset_digest,
    held_out_split,
    mirrored,
    seen_split,
    shipped_split_and_frames,
)
from training.pose.user_mocap import user_clips
from training.run_labels import label_run
from training.shipping import ship_files, with_registry
from training.tracking import log_onnx_model, maybe_promote, register_model, setup_tracking

log = logging.getLogger(__name__)

VAL_SEED, TEST_SEED = 11, 12
SELECTION_METRIC = "val_mae_deg"
HELD_OUT = "held-out subjects (simulated flex sensors)"


@dataclass
class FlexData:
    train: list[FlexClip]
    val: list[FlexClip]
    test: list[FlexClip]
    digest_train: str
    digest_val: str
    bandai: bool
    source: str = ""  # the data directory
    # with ``data.seen_share``: training clips held back (Chen et al. 2024 §3.3's protocol)
    seen: list[FlexClip] = field(default_factory=list)


def load_flex_data(cfg: FlexConfig, data_dir: Path, cache_dir: Path, workers: int = 2) -> FlexData:
    d = cfg.data
    entries = mocap_entries(data_dir, sources=d.sources)
    clips = build_motions(data_dir, entries, cache_dir, workers, limb_twist=d.limb_twist, trunk_axes=d.trunk_axes)
    train, val, test = held_out_split(clips, d.test_subjects, d.val_subjects, d.test_activities_of_unlabelled)
    train, seen = seen_split(train, d.seen_share) if d.seen_share > 0 else (train, [])
    if d.mirror:
        train = train + [mirrored(c) for c in train]
    log.info("flex split: %d train, %d validation, %d test clips", len(train), len(val), len(test))
    conv = lambda cl: [flex_clip(c, cfg.joints, cfg.sensors, cfg.model.window) for c in cl]  # noqa: E731
    return FlexData(
        conv(train),
        conv(val),
        conv(test),
        dataset_digest(train),
        dataset_digest(val),
        any(is_bandai_namco(c.source) for c in train),
        str(data_dir),
        conv(seen),
    )


def user_flex_data(
    cfg: FlexConfig,
    paths: list[Path],
    mapping: Path | None,
    data_dir: Path | None,
    cache_dir: Path,
    skipped: list[dict[str, str]] | None = None,
) -> FlexData:
    """A user's BVH files or folders as the test part (``training.pose.user_mocap.user_clips``: a mapping file for
    an unknown skeleton, the activity the folder's name, a file that cannot be scored left out into ``skipped``),
    in the segment frames ``cfg`` names; nothing to train on or validate by."""
    d = cfg.data
    clips = user_clips(paths, mapping, d.limb_twist, data_dir, cache_dir, skipped, d.trunk_axes)
    test = [flex_clip(c, cfg.joints, cfg.sensors, cfg.model.window) for c in clips]
    return FlexData([], [], test, "", "", False, ", ".join(str(p) for p in paths))


def held_out_metrics(test: dict, ageing: dict[float, dict], replaced: dict) -> dict[str, float]:
    """A manifest's held-out figures of a model (its run's, or ``evaluate-flex --record``'s)."""
    metrics = {k: round(v, 4) for k, v in flat_metrics(test, "test").items() if "_joint_" not in k}
    metrics |= {f"test_ageing_{int(100 * b)}pct_mae_deg": round(v["mae_deg"], 4) for b, v in ageing.items()}
    return metrics | {"test_replaced_mae_deg": round(replaced["mae_deg"], 4)}


def evaluation_digest(cfg: FlexConfig, data: FlexData) -> str:
    """The registry's ``eval_digest`` of a validation figure: the validation clips, and "|hinge-zeros" where the
    answer holds the hinge frames' zeros (``answer_mask``, since 2026-12-07): a figure scored one way is not compared
    with one scored the other."""
    return data.digest_val + ("|hinge-zeros" if answer_mask(cfg) is not None else "")


def clip_table(clips: list[FlexClip]) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "path": [c.path for c in clips],
            "source": [c.source for c in clips],
            "subject": [c.group for c in clips],
            "activity": [c.activity for c in clips],
            "frames_20hz": [c.frames for c in clips],
        }
    )


def log_datasets(tables: dict[str, pd.DataFrame], source: str, prefix: str) -> None:
    """One MLflow dataset input per context (train, validation, test), named by its content's digest."""
    for context, table in tables.items():
        digest = hashlib.sha256(table.to_csv(index=False).encode()).hexdigest()[:20]
        mlflow.log_input(
            mlflow.data.from_pandas(table, source=source, name=f"{prefix}-{context}-{digest}"), context=context
        )


def ageing_set(ws: WindowSet, seed: int, baseline0: float) -> WindowSet:
    """The same clips read by suits aged to ``baseline0`` (share of R0) at the start; every other parameter as
    the clip's test suit."""

    def counts(c: FlexClip, k: int) -> np.ndarray:
        suit, s = clip_suit(seed, c.path, k, c.bend.shape[1], baseline0=baseline0)
        return simulate_counts(c.bend, suit, np.random.default_rng(s + 1))

    return window_set(ws.clips, 1, seed, ws.window, counts_fn=counts)


def other_lot_set(ws: WindowSet, seed: int) -> WindowSet:
    """The same clips read by suits of another lot: every sensor's curve over the datasheet's whole tolerance."""

    def counts(c: FlexClip, k: int) -> np.ndarray:
        s = clip_seed(seed + 200, c.path, k)
        suit = draw_suit(np.random.default_rng(s), c.bend.shape[1], lot=False)
        return simulate_counts(c.bend, suit, np.random.default_rng(s + 1))

    return window_set(ws.clips, 1, seed, ws.window, counts_fn=counts)


def replacement_set(ws: WindowSet, seed: int) -> WindowSet:
    """One sensor per clip (drawn) swapped for a new one half-way through the clip's motion."""

    def counts(c: FlexClip, k: int) -> np.ndarray:
        suit, s = clip_suit(seed, c.path, k, c.bend.shape[1])
        rng = np.random.default_rng(clip_seed(seed + 100, c.path, k))
        sensor = int(rng.integers(c.bend.shape[1]))
        at = {sensor: (c.pad + c.frames // 2, draw_sensor(rng, lot=False))}
        return simulate_counts(c.bend, suit, np.random.default_rng(s + 1), replace_at=at)

    return window_set(ws.clips, 1, seed, ws.window, counts_fn=counts)


def run_time_ms(predict, ws: WindowSet, n: int = 256) -> float:
    """Per-window run time of one batch of ``n`` windows, as Table 5's run time (ms per window)."""
    x, _ = ws.batch(np.zeros(n, int), ws.ends[:n], 1)
    predict(x)
    t0 = time.perf_counter()
    for _ in range(3):
        predict(x)
    return (time.perf_counter() - t0) / 3 / n * 1e3


def _trace(predict, ws: WindowSet, latency: int, cfg: FlexConfig, path: Path, title: str) -> Path:
    """The sensors' own flexion angles (knees and elbows) over the first test clip with walking in it."""
    i = next((k for k, c in enumerate(ws.clips) if c.activity == "walk" and c.frames > 200), 0)
    m = np.flatnonzero(ws.clip_of_end == i)[:400]
    x, _ = ws.batch(np.zeros(len(m), int), ws.ends[m], 1)
    pred = predict(x)
    truth = ws.angles[ws.ends[m] - 1 - latency]
    js = [cfg.joints.index(j) for j in cfg.sensors if j in cfg.joints]
    names = [cfg.joints[j] for j in js]
    return traces_png(
        np.arange(len(m)) / FLEX_RATE_HZ,
        {n: truth[:, j, 0] for n, j in zip(names, js, strict=True)},
        {n: pred[:, j, 0] for n, j in zip(names, js, strict=True)},
        path,
        title,
    )


def run_flex_experiment(
    cfg: FlexConfig,
    data: FlexData,
    sets: dict[str, WindowSet],
    ship_to: Path | None = None,
    version: str | None = None,
) -> dict:
    """Train, evaluate, export, log and register one flex network; ship it under ``ship_to/<name>/<version>``."""
    setup_tracking(cfg.tracking.experiment)
    with mlflow.start_run(run_name=cfg.name) as run, tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        mlflow.set_tags(
            {
                "task": "flex_pose",
                "variant": cfg.variant,
                "mlflow.note.content": f"{cfg.variant} (Chen et al. 2024 Table 5) from {len(cfg.sensors)} simulated "
                f"flex sensors ({', '.join(cfg.sensors)}) to {len(cfg.joints)} joints x 3 angles. Validation "
                "subjects choose, held-out subjects are reported.",
                "trains_on_bandai_namco": str(data.bandai),
            }
        )
        mlflow.log_params({k: str(v) for k, v in flatten(cfg.model_dump()).items()})
        tables = {"train": clip_table(data.train), "validation": clip_table(data.val), "test": clip_table(data.test)}
        log_datasets(tables, data.source, "flex")
        result: FlexTrainResult = train_flex(
            cfg,
            sets["train"],
            sets["val"],
            on_epoch=lambda e, row: mlflow.log_metrics(
                {"train_loss": row["train_loss"], "val_mae_deg_epoch": row["val_mae_deg"]}, step=e
            ),
        )
        net = result.net
        mlflow.log_metrics(
            {"best_epoch": result.best_epoch, "train_wall_time_s": result.wall_s, "epochs_run": len(result.history)}
        )
        mlflow.set_tag("stopped", result.stopped)
        label_run(MlflowClient(), run.info.run_id)  # its name and description in the UI
        mlflow.log_artifact(str(flex_learning_curve_png(result.history, tmp / "learning_curve.png", cfg.name)), "plots")
        predict = torch_predictor(net, answer_mask(cfg))  # as the service answers
        lat = net.latency_samples
        val = clip_metrics(predict, sets["val"], 0, lat, cfg.joints, cfg.sensors)
        test = clip_metrics(predict, sets["test"], 0, lat, cfg.joints, cfg.sensors)
        mlflow.log_metrics(flat_metrics(val, "val") | flat_metrics(test, "test"))
        if data.seen:  # other takes of the training people: Chen et al. 2024 §3.3's test, not ours
            seen_set = window_set(data.seen, 1, TEST_SEED, cfg.model.window)
            seen = clip_metrics(predict, seen_set, 0, lat, cfg.joints, cfg.sensors)
            mlflow.log_metrics(flat_metrics(seen, "seen"))
            log.info("seen people (%d training clips held back): %.2f°", len(data.seen), seen["mae_deg"])
        mean = sets["train"].angles.mean(axis=0)
        baseline = clip_metrics(mean_pose_predictor(mean), sets["test"], 0, lat, cfg.joints, cfg.sensors)
        mlflow.log_metrics(flat_metrics(baseline, "test_meanpose"))
        ageing = ageing_curve(predict, aged(sets, "ageing_"), lat, cfg)
        # the same on the validation suits: what a choice made for ageing may look at
        val_ageing = ageing_curve(predict, aged(sets, "val_ageing_"), lat, cfg)
        for split, curve in (("test", ageing), ("val", val_ageing)):
            for b, v in curve.items():
                mlflow.log_metrics(
                    {f"{split}_ageing_mae_deg": v["mae_deg"], f"{split}_ageing_jitter": v["jitter_deg_s3"]},
                    step=int(b * 100),
                )
        replaced = clip_metrics(predict, sets["replaced"], 0, lat, cfg.joints, cfg.sensors)
        mlflow.log_metrics(flat_metrics(replaced, "test_replaced"))
        other_lot = clip_metrics(predict, sets["other_lot"], 0, lat, cfg.joints, cfg.sensors)
        mlflow.log_metrics(flat_metrics(other_lot, "test_other_lot"))
        run_ms = run_time_ms(predict, sets["test"])
        mlflow.log_metric("run_time_ms_per_window", run_ms)
        for name, values, unit in (
            ("joint_errors_test", test["per_joint"], "mean tracking error (deg)"),
            (
                "activity_errors_test",
                {a: v["mae_deg"] for a, v in test["per_activity"].items()},
                "mean tracking error (deg)",
            ),
        ):
            mlflow.log_artifact(
                str(bars_png(values, tmp / f"{name}.png", f"{cfg.name}: held-out subjects", unit, cfg.sensors)), "plots"
            )
        mlflow.log_artifact(
            str(
                curves_png(
                    [100 * b for b in AGEING_BEYOND],
                    {cfg.variant: [ageing[b]["mae_deg"] for b in AGEING_BEYOND]},
                    tmp / "ageing_error.png",
                    f"{cfg.name}: error against sensor ageing (training range 0-15 %)",
                    "baseline resistance rise at the session's start (% of R0)",
                    "mean tracking error (deg)",
                )
            ),
            "plots",
        )
        mlflow.log_artifact(str(_trace(predict, sets["test"], lat, cfg, tmp / "trace_walk.png", cfg.name)), "plots")
        summary = {
            "variant": cfg.variant,
            "run_id": run.info.run_id,
            "val": val,
            "test": test,
            "mean_pose": baseline,
            "ageing": ageing,
            "replaced": replaced,
            "other_lot": other_lot,
            "train_wall_time_s": result.wall_s,
            "best_epoch": result.best_epoch,
            "epochs_run": len(result.history),
            "stopped": result.stopped,
            "run_time_ms_per_window": run_ms,
            "latency_samples": lat,
        }
        (tmp / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
        mlflow.log_artifact(str(tmp / "summary.json"), "evaluation")

        onnx_path = export_flex_onnx(net, tmp / "model.onnx")
        x, _ = sets["test"].batch(np.zeros(8, int), sets["test"].ends[:: max(1, len(sets["test"].ends) // 8)][:8], 1)
        # the file's own output, before the service's answer mask (FlexModel.answer_mask)
        golden = {"counts": x.astype(np.float32), "expected": torch_predictor(net)(x).astype(np.float32)}
        parity = onnx_parity(onnx_path, golden)
        mlflow.log_metric("onnx_parity_max_abs", parity)
        if parity > 1e-3:
            raise RuntimeError(f"onnxruntime differs from torch by {parity:.2e} deg on the golden input")
        np.savez(tmp / "golden.npz", **golden)
        version = version or "0.0.0+" + run.info.run_id[:8]
        training_data = {
            "sources": sorted({c.source for c in data.train}),
            "train_clips": len(data.train),
            "train_frames_20hz": int(sum(c.frames for c in data.train)),
            "simulated_suits_per_clip": cfg.data.suits_per_clip,
            "validation_subjects": cfg.data.val_subjects,
            "test_subjects": cfg.data.test_subjects,
            "test_unlabelled_clips": cfg.data.test_activities_of_unlabelled,
            # the segment frames its angles are in (evaluate-flex scores in them)
            "limb_twist": cfg.data.limb_twist,
            "trunk_axes": cfg.data.trunk_axes,
            "bandai_namco": data.bandai,
            "train_wall_time_s": round(result.wall_s, 1),
            "best_epoch": result.best_epoch,
            "epochs_run": len(result.history),
            "stopped": result.stopped,
        } | ({"licence": BANDAI_LICENCE} if data.bandai else {})
        if cfg.data.seen_share:  # trained without a share of the training clips
            training_data["seen_share"] = cfg.data.seen_share
        metrics = held_out_metrics(test, ageing, replaced) | {"test_meanpose_mae_deg": round(baseline["mae_deg"], 4)}
        evaluation = Evaluation(
            name=HELD_OUT,
            command=f"python -m training.cli evaluate-flex --model onnx_models/{cfg.name}/{version}",
            data=f"CMU subjects {', '.join(cfg.data.test_subjects)} and the li2018 run clips, never trained on or "
            f"chosen by; one simulated suit per clip (seed {TEST_SEED}); ageing: the same suits aged at the start",
            metrics=metrics,
        )
        manifest = build_flex_manifest(
            cfg,
            net,
            version,
            sha256_file(onnx_path),
            training_data,
            [evaluation],
            {"run_id": run.info.run_id, "experiment_id": run.info.experiment_id},
        )
        proto = onnx.load(str(onnx_path))
        info = log_onnx_model(proto, golden, manifest, input_key="counts")
        mlflow.set_tag("model_uri", info.model_uri)
        registered = register_model(info.model_uri, cfg.registered_model)
        promoted = maybe_promote(
            cfg.registered_model,
            registered.version,
            SELECTION_METRIC,
            val["mae_deg"],
            False,
            evaluation_digest(cfg, data),
        )
        mlflow.set_tag("promoted_to_champion", str(promoted))
        manifest = with_registry(manifest, info, registered)
        if ship_to is not None:
            shipped = ship_files(ship_to, manifest, onnx_path, tmp / "golden.npz")
            served = FlexModel(load_model(shipped, 2))  # the served path must score as torch did
            a = clip_metrics(served.run_windows, sets["test"], 0, lat, cfg.joints, cfg.sensors)["mae_deg"]
            if abs(a - test["mae_deg"]) > 0.02:
                raise RuntimeError(f"the shipped model scores {a:.3f}° where torch scored {test['mae_deg']:.3f}°")
            summary["shipped"] = str(shipped)
            log.info("shipped %s", shipped)
        return summary


def shipped_config(m) -> FlexConfig:
    """The config a shipped simulated-suit model's clips are built and scored with, from its manifest: its joints,
    strips and window, the split its run had, and the segment frames its angles are in ("rig" and "spine" where
    the manifest does not say)."""
    return FlexConfig(
        name=m.name,
        joints=m.joints,
        sensors=[c.removesuffix("_flex") for c in m.channels],
        model={"window": m.window_samples},
        data=shipped_split_and_frames(m.training_data),
    )


def evaluate_served(loaded, data: FlexData, validation: bool = False) -> dict:
    """A loaded ONNX flex model on the test sets ``build_sets`` makes (same seeds as its training run), or with
    ``validation`` on the validation suits its run chose its epoch and the registry its champion by, and those
    suits aged beyond the training range."""
    m = loaded.manifest
    cfg = shipped_config(m)
    lat = m.flex.latency_samples
    run = FlexModel(loaded).run_windows  # as the service answers
    if validation:
        val = window_set(data.val, 1, VAL_SEED, cfg.model.window)
        return {
            "model": f"{m.name} {m.version}",
            "val": clip_metrics(run, val, 0, lat, cfg.joints, cfg.sensors),
            "ageing": ageing_curve(run, {b: ageing_set(val, VAL_SEED, b) for b in AGEING_BEYOND}, lat, cfg),
        }
    sets = build_sets(cfg, data, train=False)
    score = lambda key: clip_metrics(run, sets[key], 0, lat, cfg.joints, cfg.sensors)  # noqa: E731
    return {
        "model": f"{m.name} {m.version}",
        "test": score("test"),
        "ageing": ageing_curve(run, aged(sets, "ageing_"), lat, cfg),
        "replaced": score("replaced"),
        "other_lot": score("other_lot"),
    }


def aged(sets: dict[str, WindowSet], prefix: str) -> dict[float, WindowSet]:
    """``build_sets``' suits aged to each share of ``AGEING_BEYOND``: ``prefix`` "ageing_" (test) or "val_ageing_"."""
    return {b: sets[f"{prefix}{b}"] for b in AGEING_BEYOND}


def ageing_curve(predict, aged_sets: dict[float, WindowSet], lat: int, cfg: FlexConfig) -> dict[float, dict]:
    """Error and jitter on the same suits aged to each share (``aged_sets[b]``)."""
    scores = {b: clip_metrics(predict, ws, 0, lat, cfg.joints, cfg.sensors) for b, ws in aged_sets.items()}
    return {b: {"mae_deg": s["mae_deg"], "jitter_deg_s3": s["jitter_deg_s3"]} for b, s in scores.items()}


def build_sets(cfg: FlexConfig, data: FlexData, train: bool = True) -> dict[str, WindowSet]:
    """Training suits (``suits_per_clip``, seed ``cfg.seed``), one fixed suit per validation and test clip, the
    test and validation clips under ageing beyond the training range and the test clips with a sensor replaced.
    Evaluating (``train`` False) clips without a validation part (a user's own), the validation sets are left out."""
    w = cfg.model.window
    sets = {"test": window_set(data.test, 1, TEST_SEED, w)}
    if train or data.val:  # a user's own clips (``evaluate-flex PATHS``) have no validation part
        sets["val"] = window_set(data.val, 1, VAL_SEED, w)
    if train:
        sets["train"] = window_set(
            data.train,
            cfg.data.suits_per_clip,
            cfg.seed,
            w,
            cfg.data.activity_cap_frames,
            bandai_share=cfg.data.bandai_share,
        )
    for b in AGEING_BEYOND:
        sets[f"ageing_{b}"] = ageing_set(sets["test"], TEST_SEED, b)
        if "val" in sets:
            sets[f"val_ageing_{b}"] = ageing_set(sets["val"], VAL_SEED, b)
    sets["replaced"] = replacement_set(sets["test"], TEST_SEED)
    sets["other_lot"] = other_lot_set(sets["test"], TEST_SEED)
    return sets


def summary_table(results: list[dict]) -> pd.DataFrame:
    rows = []
    for r in results:
        rows.append(
            {
                "method": r["variant"],
                "tracking_error_deg": r["test"]["mae_deg"],
                "sensed_flexion_error_deg": r["test"]["sensed_flexion_mae_deg"],
                "training_time_min": r["train_wall_time_s"] / 60,
                "epochs": r["epochs_run"],
                "run_time_ms": r["run_time_ms_per_window"],
                "jitter_1e4_deg_s3": r["test"]["jitter_deg_s3"] / 1e4,
                "latency_samples": r["latency_samples"],
                f"aged_{int(100 * AGEING_BEYOND[-2])}pct_error_deg": r["ageing"][AGEING_BEYOND[-2]]["mae_deg"],
                f"aged_{int(100 * AGEING_BEYOND[-2])}pct_jitter_1e4": r["ageing"][AGEING_BEYOND[-2]]["jitter_deg_s3"]
                / 1e4,
                "sensor_replaced_error_deg": r["replaced"]["mae_deg"],
                "other_lot_error_deg": r["other_lot"]["mae_deg"],
                "val_error_deg": r["val"]["mae_deg"],
            }
        )
    rows.append({"method": "mean pose", "tracking_error_deg": results[0]["mean_pose"]["mae_deg"]})
    return pd.DataFrame(rows)


def markdown_table(df: pd.DataFrame) -> str:
    """A DataFrame as a Markdown table, numbers to three significant digits (blank where missing)."""

    def cell(v: object) -> str:
        if v is None or (isinstance(v, float) and not np.isfinite(v)):
            return ""
        return f"{v:.3g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(df.columns) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join(lines)


def log_summary_run(results: list[dict], experiment: str) -> str:
    """One run holding Chen et al. 2024 Table 5 for our data: the table (CSV, Markdown), the bar chart and the
    ageing curves of every network."""
    setup_tracking(experiment)
    table = summary_table(results)
    with mlflow.start_run(run_name="flex_table5_summary") as run, tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        mlflow.set_tags({"task": "flex_pose", "mlflow.note.content": "Chen et al. 2024 Table 5 on held-out subjects"})
        (tmp / "table5.csv").write_text(table.to_csv(index=False))
        (tmp / "table5.md").write_text(markdown_table(table))
        mlflow.log_artifacts(str(tmp), "table")
        for r in results:
            mlflow.log_metrics(
                {
                    f"{r['variant']}_test_mae_deg": r["test"]["mae_deg"],
                    f"{r['variant']}_test_jitter": r["test"]["jitter_deg_s3"],
                }
            )
        bars = {r["variant"]: r["test"]["mae_deg"] for r in results} | {"mean pose": results[0]["mean_pose"]["mae_deg"]}
        mlflow.log_artifact(
            str(bars_png(bars, tmp / "table5_error.png", "held-out subjects", "mean tracking error (deg)")), "plots"
        )
        jit = {r["variant"]: r["test"]["jitter_deg_s3"] / 1e4 for r in results}
        mlflow.log_artifact(
            str(bars_png(jit, tmp / "table5_jitter.png", "held-out subjects", "jitter (1e4 deg/s^3)")), "plots"
        )
        x = [100 * b for b in AGEING_BEYOND]
        for key, label in (("mae_deg", "mean tracking error (deg)"), ("jitter_deg_s3", "jitter (deg/s^3)")):
            curves = {r["variant"]: [r["ageing"][b][key] for b in AGEING_BEYOND] for r in results}
            mlflow.log_artifact(
                str(
                    curves_png(
                        x,
                        curves,
                        tmp / f"ageing_{key}.png",
                        "ageing beyond the training range (0-15 %)",
                        "baseline resistance rise at the session's start (% of R0)",
                        label,
                    )
                ),
                "plots",
            )
        return run.info.run_id
